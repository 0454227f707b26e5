"""The layout keeps its promises.

* Each vocabulary is declared once: room types, renderers and splits in protocol/vocab.py; the
  agent's explorers, depth sources and missing-top choices in agent/config.py; perception modes
  in agent/perception/__init__.py; variants and OOP detectors in their registries. Nothing else
  spells those lists out.
* Every package of the tree is installed (pyproject's packages).
* The tests mirror the source tree, and no test module imports another.
"""

from __future__ import annotations

import re
from pathlib import Path

from tests.support import REPO as SUPPORT_REPO

ROOT = SUPPORT_REPO
PARTS = ("agent", "server", "protocol", "viewer", "tidee", "examples", "tests")

# A copy: two or more of a vocabulary's words in a row, quoted, as a literal list would have them.
COPIES = {
    "room types": r'"(Kitchen|LivingRoom|Bedroom|Bathroom)",\s*"(Kitchen|LivingRoom|Bedroom|Bathroom)"',
    "renderers": r'"(auto|egl|tiny)",\s*"(egl|tiny)"',
    "splits": r'"(train|val|test)",\s*"(val|test)"',
    "explorers": r'"random",\s*"frontier"',
    "perception modes": r'"(learned|oracle)",\s*"(learned|oracle)"',
    "depth sources": r'"sensor",\s*"estimated"',
    "missing-top choices": r'"skip",\s*"search"',
    "agent variants": r'"TIDEE",\s*"WithoutMemex"',
    "OOP detectors": r'"relation_stats",\s*"visual"',
}
HOMES = {
    "room types": {"protocol/vocab.py"},
    "renderers": {"protocol/vocab.py"},
    "splits": {"protocol/vocab.py"},
    "explorers": {"agent/config.py"},
    "perception modes": {"agent/perception/__init__.py"},
    "depth sources": {"agent/config.py"},
    "missing-top choices": {"agent/config.py"},
    "agent variants": set(),  # registered one by one in agent/reasoning/placement.py
    "OOP detectors": set(),  # registered one by one in agent/reasoning/oop.py
}
# Where a list is the point of the test: the registry order the paper's tables follow.
ALLOWED = {
    ("tests/agent/test_registries.py", "agent variants"),
    ("tests/agent/test_registries.py", "OOP detectors"),
}
# Tests may name a few members as data ("Kitchen", "Bedroom"); a whole list there is still a copy.
WHOLE = {
    "room types": r'"Kitchen",\s*"LivingRoom",\s*"Bedroom",\s*"Bathroom"',
    "agent variants": r'"TIDEE",\s*"WithoutMemex",\s*"3DSmntMap2Place",\s*"CommonMemory"',
}


def test_no_vocabulary_is_spelled_out_twice() -> None:
    found = []
    for part in PARTS:
        for path in sorted((ROOT / part).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            if rel == "tests/test_layout.py":
                continue
            text = path.read_text()
            for name, pattern in COPIES.items():
                if rel in HOMES[name] or (rel, name) in ALLOWED:
                    continue
                if rel.startswith("tests/"):
                    pattern = WHOLE.get(name, pattern)
                for m in re.finditer(pattern, text):
                    line = text.count("\n", 0, m.start()) + 1
                    found.append(f"{rel}:{line}: {name}: {m.group(0)}")
    assert not found, "vocabulary copied instead of imported:\n" + "\n".join(found)


def test_the_literal_types_and_the_tuples_agree() -> None:
    from typing import get_args

    from tidee.agent import config
    from tidee.protocol import vocab

    assert vocab.ROOM_TYPES == get_args(vocab.RoomType) == ("Kitchen", "LivingRoom", "Bedroom", "Bathroom")
    assert set(vocab.HELD_OUT_SPLITS) < set(vocab.SPLITS)
    assert config.EXPLORERS == get_args(config.Explorer)
    assert config.PERCEPTIONS == get_args(config.PerceptionMode)


def test_every_package_of_the_tree_is_installed() -> None:
    """A new subpackage must be listed in pyproject's packages, or `pip install .` leaves it out."""
    import tomllib

    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    dirs = {"tidee": "tidee", "protocol": "tidee.protocol", "server": "tidee.server", "agent": "tidee.agent"}
    dirs["viewer"] = "tidee.viewer"
    found = set()
    for folder, package in dirs.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder).parts
            found.add(".".join((package, *rel)))
    assert found - listed == set(), f"not in pyproject's packages: {sorted(found - listed)}"


def test_the_tests_mirror_the_tree_and_no_test_module_imports_another() -> None:
    """tests/<part>/... follows the source tree; shared helpers live in tests/support and
    fixtures in tests/conftest.py, so no test module imports another."""
    tests = ROOT / "tests"
    for path in tests.rglob("test_*.py"):
        rel = path.relative_to(tests).parent
        if rel.parts:  # a test of a part sits in that part's folder, which exists in the source
            source = ROOT / ("tidee" if rel.parts[0] == "tidee" else rel.parts[0]) / Path(*rel.parts[1:])
            assert source.is_dir(), f"{path.relative_to(ROOT)}: no source folder {source.relative_to(ROOT)}"
        imports = re.findall(r"^\s*(?:from|import) (tests\.[\w.]+)", path.read_text(), re.M)
        bad = [m for m in imports if not m.startswith("tests.support")]
        assert not bad, f"{path.relative_to(ROOT)} imports another test module: {bad}"


def test_only_evaluation_reads_the_human_annotations() -> None:
    """The Housekeep votes judge; nothing that generates data, trains, tunes or acts may read them."""
    allowed = {
        "agent/evaluation/human_judge.py",  # the judge
        "agent/evaluation/report.py",  # its columns in tidy reports
        "agent/evaluation/config.py",  # `tidee eval human`'s options
        "tidee/cli.py",  # `tidee eval housekeep`
        "tests/agent/evaluation/test_human_judge.py",
        "tests/test_layout.py",
    }
    readers = []
    for part in PARTS:
        for path in sorted((ROOT / part).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            text = path.read_text().lower()
            if ("housekeep" in text or "human_judge" in text) and rel not in allowed:
                readers.append(rel)
    assert not readers, f"modules that mention the human annotations outside evaluation: {readers}"
