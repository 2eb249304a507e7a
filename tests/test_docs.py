"""The documentation stands on its own and agrees with the code.

- README.md, docs/, benchmarks/ and examples/ name nothing outside the repository (a
  reader has only the clone): no ``../shared``, no ``/work/``, no ``/root/``.
- README.md links every document in docs/, and every relative link resolves.
- docs/scenarios.md names every key of every scenario table (the config dataclasses
  the TOML loader builds), and the keys of the planned ``[search]`` table.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FOREIGN = ("../shared", "/work/", "/root/")
TEXT_SUFFIXES = {".md", ".py", ".toml", ".txt", ".sh", ".cfg", ".ini", ".json", ".jsonl", ""}


def _public_files() -> list[Path]:
    files = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*"))]
    for folder in ("benchmarks", "examples", "tools"):
        files += sorted((ROOT / folder).rglob("*"))
    return [f for f in files if f.is_file() and f.suffix in TEXT_SUFFIXES
            and "__pycache__" not in f.parts]


def foreign_references(text: str) -> list[str]:
    return [needle for needle in FOREIGN if needle in text]


def test_the_checker_finds_foreign_paths():
    assert foreign_references("see ../shared/spec/cli.md") == ["../shared"]
    assert foreign_references("run /work/venv/bin/python x.py") == ["/work/"]
    assert foreign_references("python benchmarks/bench_upload.py") == []


@pytest.mark.parametrize("path", _public_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_nothing_outside_the_repository_is_named(path):
    text = path.read_text(encoding="utf-8", errors="replace")
    bad = [(i + 1, line.strip()) for i, line in enumerate(text.splitlines())
           if foreign_references(line)]
    assert not bad, f"{path.relative_to(ROOT)} names paths outside the repository: {bad}"


def test_readme_links_every_document():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    docs = sorted(p.name for p in (ROOT / "docs").glob("*.md"))
    assert {"log-format.md", "cli.md", "scenarios.md", "architecture.md",
            "reproduce-paper.md"} <= set(docs)
    for name in docs:
        assert f"](docs/{name})" in readme, f"README.md does not link docs/{name}"


@pytest.mark.parametrize("doc", [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))],
                         ids=lambda p: p.name)
def test_relative_links_resolve(doc):
    text = doc.read_text(encoding="utf-8")
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue  # a URL or an anchor
        path = (doc.parent / target.split("#")[0]).resolve()
        assert path.exists(), f"{doc.name}: broken link {target}"


def test_the_paper_is_cited():
    for doc in ("README.md", "docs/reproduce-paper.md"):
        text = (ROOT / doc).read_text(encoding="utf-8")
        assert "arXiv:2606.00075" in text
        assert "Towards Networked One Search Agent" in text and "Bravo-Arrabal" in text


# ----------------------------------------------------------------- scenarios.md


def _scenario_classes() -> dict[str, type]:
    from sim.clock import ClockConfig
    from sim.flights import FLIGHT_KINDS, Circle, ClosePass
    from sim.ftm import ConcealmentModel, FtmConfig, RangeNoiseConfig
    from sim.gnss import GnssConfig
    from sim.scenario import LogSettings
    from sim.terrain import Hill, HillsTerrain
    from sim.vehicle import VehicleConfig
    from sim.world import Origin, Responder

    classes = [VehicleConfig, GnssConfig, FtmConfig, ConcealmentModel, RangeNoiseConfig,
               ClockConfig, LogSettings, Origin, HillsTerrain, Hill, Responder, Circle,
               ClosePass, *FLIGHT_KINDS.values()]
    # the tables of the closed loop, once the loader reads them ([search], [[agents]])
    import sim.scenario

    classes += [c for n in ("SearchSpec", "AgentSpec") if (c := getattr(sim.scenario, n, None))]
    return {c.__name__: c for c in classes}


def _keys_in_doc() -> set[str]:
    """Names written as code in docs/scenarios.md: `key`, and the parts of `[a.b]`."""
    text = (ROOT / "docs" / "scenarios.md").read_text(encoding="utf-8")
    keys = set(re.findall(r"`([a-z_][a-z0-9_]*)", text))
    for table in re.findall(r"`\[{1,2}([a-z0-9_.]+)\]{1,2}`", text):
        keys |= set(table.split("."))
    return keys


@pytest.mark.parametrize("cls", sorted(_scenario_classes()))
def test_scenario_doc_names_every_field(cls):
    fields = [f.name for f in dataclasses.fields(_scenario_classes()[cls]) if f.init]
    missing = sorted(set(fields) - _keys_in_doc())
    assert not missing, f"docs/scenarios.md does not name {cls} fields {missing}"


def test_scenario_doc_names_the_other_keys():
    from sim.flights import FLIGHT_KINDS
    from sim.gnss import GNSS_PRESETS

    keys = _keys_in_doc()
    text = (ROOT / "docs" / "scenarios.md").read_text(encoding="utf-8")
    # keys the loader reads itself, outside the dataclasses
    assert {"name", "description", "extends", "kind", "preset", "file", "heights_m", "e0_m",
            "n0_m", "spacing_m", "lat_deg", "lon_deg"} <= keys
    for kind in FLIGHT_KINDS:
        assert f'`kind = "{kind}"`' in text
    for preset in GNSS_PRESETS:
        assert f'"{preset}"' in text
    for table in ("[log]", "[world.origin]", "[world.terrain]", "[[world.responders]]",
                  "[flight]", "[[flight.circles]]", "[flight.close_pass]", "[vehicle]",
                  "[gnss]", "[ftm]", "[ftm.noise]", "[ftm.open]", "[ftm.vegetation]",
                  "[ftm.vegetation_debris]", "[clock]", "[search]"):
        assert f"`{table}`" in text, table


def test_scenario_doc_has_the_search_table():
    text = (ROOT / "docs" / "scenarios.md").read_text(encoding="utf-8")
    search = text[text.index("## `[search]`"):]
    assert "used by `osa search`" in search
    for key in ("area_enu_m", "start_e_m", "start_n_m", "budget_s", "height_m", "speed_mps",
                "random_responders", "random_concealment"):
        assert f"`{key}`" in search, key


def test_scenario_doc_example_loads(tmp_path):
    import sim

    text = (ROOT / "docs" / "scenarios.md").read_text(encoding="utf-8")
    body = re.search(r"```toml\n(.*?)```", text, re.S).group(1)
    path = tmp_path / "my-field.toml"
    path.write_text(body, encoding="utf-8")
    sc = sim.load_scenario(path)
    assert sc.name == "my-field" and sc.gnss.fix == "rtk_fixed"
    assert [r.name for r in sc.world.responders] == ["PHONE_1"]
    assert sc.flight.close_pass.target == "PHONE_1" and len(sc.flight.circles) == 2


def test_a_class_table_replaces_the_whole_model(tmp_path):
    """What docs/scenarios.md says of [ftm.vegetation]: left-out keys are open's."""
    import sim
    from sim.ftm import OPEN

    path = tmp_path / "veg.toml"
    path.write_text('extends = "paper-ap1f"\n[ftm.vegetation]\nattenuation_db = 6.0\n')
    veg = sim.load_scenario(path).ftm.vegetation
    assert veg.attenuation_db == 6.0
    assert dataclasses.replace(veg, attenuation_db=OPEN.attenuation_db) == OPEN
