"""PPO kept near an imitated policy: an imitation term and a critic warm-up (docs/rl.md).

:class:`GuidedPPO` is Stable-Baselines3's PPO with two additions for a training that
starts from a clone of the hand-written policy (``osa train --imitate N --dagger K``):

- **imitation term** (``imitation_coef``, ``osa train --imitation-coef X``): every PPO
  gradient step also descends ``coef * CE``, the cross-entropy of the policy to the
  teacher's labels on a minibatch (PPO's size) of the imitation dataset (the DAgger
  states, normalised with the current statistics), ``coef`` falling linearly from X to
  0 over the training. The term's gradient is added to PPO's clipped gradient just
  before the optimiser's step (a step pre-hook), so one Adam step sees
  ``PPO loss + coef * CE`` (behaviour-cloning regularisation; a loss-scale weight
  matters only inside one joint step: Adam is invariant to the scale of a loss stepped
  alone).
- **critic warm-up** (``critic_warmup``, ``osa train --critic-warmup K``): during the
  first K updates (rollouts) the actor's parameters do not take gradients, so PPO's
  epochs fit only the value head to the returns of the clone's own rollouts before the
  advantages it computes move the actor.

PPO's own update (:meth:`stable_baselines3.PPO.train`) is not restated; the model
saves and loads as any PPO model (``ppo:MODEL``, :class:`envs.gym.trained.TrainedPolicy`):
the dataset is not saved with it.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.utils import obs_as_tensor


class GuidedPPO(PPO):
    """PPO with an annealed imitation term and a critic warm-up (see the module
    docstring). ``imitation_seed`` seeds the draw of the imitation minibatches."""

    def __init__(self, *args, imitation_coef: float = 0.0, critic_warmup: int = 0,
                 imitation_seed: int = 0, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        if not (np.isfinite(imitation_coef) and imitation_coef >= 0):
            raise ValueError("imitation_coef must be >= 0")
        if critic_warmup < 0:
            raise ValueError("critic_warmup must be >= 0")
        self.imitation_coef = float(imitation_coef)
        self.critic_warmup = int(critic_warmup)
        self.updates_done = 0
        self._imitation: tuple[dict[str, np.ndarray], np.ndarray] | None = None
        self._normalise: Callable[[dict], dict] | None = None
        self._imitation_rng = np.random.default_rng(imitation_seed)
        self._ce: list[float] = []

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_imitation", "_normalise",
                "_imitation_rng", "_ce"]

    def set_imitation_data(self, obs: dict[str, np.ndarray], labels: np.ndarray,
                           normalise: Callable[[dict], dict]) -> None:
        """The imitation dataset: raw observations (one array per key), the teacher's
        actions, and the observation normalisation applied at each use (the current
        ``VecNormalize`` statistics)."""
        labels = np.asarray(labels, dtype=np.int64)
        if any(len(v) != len(labels) for v in obs.values()) or len(labels) == 0:
            raise ValueError("the imitation dataset needs one label per observation")
        self._imitation = (obs, labels)
        self._normalise = normalise

    def actor_parameters(self) -> list[torch.nn.Parameter]:
        """The parameters the actor depends on and the critic does not need to fit:
        all but the value head, the value branch of the MLP and a critic-only feature
        extractor (a shared extractor counts as the actor's: freezing it leaves the
        action distribution exactly as it was)."""
        p = self.policy
        critic = [p.value_net, p.mlp_extractor.value_net]
        if not p.share_features_extractor:
            critic.append(p.vf_features_extractor)
        ids = {id(x) for m in critic for x in m.parameters()}
        return [x for x in p.parameters() if id(x) not in ids]

    def imitation_ce(self, idx: np.ndarray | None = None) -> torch.Tensor:
        """The mean cross-entropy of the policy to the teacher's labels (on the dataset
        rows ``idx``, all by default), with gradients."""
        assert self._imitation is not None and self._normalise is not None
        obs, labels = self._imitation
        if idx is None:
            idx = np.arange(len(labels))
        o = self._normalise({k: v[idx] for k, v in obs.items()})
        o_t = obs_as_tensor(o, self.policy.device)
        dist = self.policy.get_distribution(o_t)
        return -dist.log_prob(torch.as_tensor(labels[idx], device=self.policy.device)).mean()

    def _imitation_step(self, coef: float) -> None:
        assert self._imitation is not None
        idx = self._imitation_rng.integers(len(self._imitation[1]), size=self.batch_size)
        with torch.enable_grad():
            ce = self.imitation_ce(idx)
            (coef * ce).backward()
        self._ce.append(float(ce.item()))

    def train(self) -> None:
        warm = self.updates_done < self.critic_warmup
        self.updates_done += 1
        coef = self.imitation_coef * self._current_progress_remaining
        frozen = self.actor_parameters() if warm else []
        for x in frozen:
            x.requires_grad_(False)
        hook = None
        self._ce = []
        if not warm and coef > 0 and self._imitation is not None:
            hook = self.policy.optimizer.register_step_pre_hook(
                lambda opt, args, kwargs: self._imitation_step(coef))
        try:
            super().train()
        finally:
            for x in frozen:
                x.requires_grad_(True)
            if hook is not None:
                hook.remove()
        self.logger.record("train/critic_warmup", int(warm))
        self.logger.record("train/imitation_coef", 0.0 if warm else coef)
        if self._ce:
            self.logger.record("train/imitation_ce", float(np.mean(self._ce)))
