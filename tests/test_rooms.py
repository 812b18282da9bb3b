"""The app of ``dslearn-run`` stays in rooms by role (issue 34): no module of :mod:`dslearn.app`, nor its
entry point :mod:`dslearn.run`, grows past :data:`MAX_LINES` lines. A room that outgrows it is split by
role (a new module of ``dslearn/app/``), not given a larger limit."""

from __future__ import annotations

from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "dslearn"
#: the most lines a module of the app may have
MAX_LINES = 400
ROOMS = sorted((PKG / "app").glob("*.py")) + [PKG / "run.py"]


def test_the_limit_sees_every_room():
    """The rooms are found (a renamed folder must not leave the limit checking nothing)."""
    names = {p.stem for p in ROOMS}
    assert {"__init__", "run", "job", "record"} <= names, names


@pytest.mark.parametrize("path", ROOMS, ids=lambda p: p.relative_to(PKG).as_posix())
def test_no_room_exceeds_the_limit(path):
    lines = len(path.read_text(encoding="utf-8").splitlines())
    assert lines <= MAX_LINES, (f"dslearn/{path.relative_to(PKG).as_posix()} has {lines} lines (at most {MAX_LINES}): "
                                "split it by role into another module of dslearn/app/")
