"""``egosurg people`` as a reviewer meets it on a recording with nobody in it: the sim's empty
operating room, recorded by the whole rig (one stereo set; the same recording as the room's
background, as docs/replay.md says for short spans). Nobody is found, so the command says so in
one line, exits 1 and writes no people file (an empty file is no trajectory file the review
tools could read)."""

from __future__ import annotations

import pytest

from protocol.cli import main


@pytest.fixture(scope="module")
def empty_room(tmp_path_factory):
    from sim.eval_set import EvalSetSpec, write_eval_set

    root = tmp_path_factory.mktemp("empty_room")
    spec = EvalSetSpec(phases=("empty",), fps=2.0, sets=1, instants=1, view_size_px=(64, 40))
    write_eval_set(root, spec)
    return root / "empty" / "session.h5"


def test_nobody_found_exits_1_with_one_line_and_writes_no_file(empty_room, tmp_path, capsys):
    out = tmp_path / "people.toml"
    capsys.readouterr()
    code = main(["people", str(empty_room), "--out", str(out), "--background", str(empty_room)])
    err = capsys.readouterr().err
    assert code == 1
    said = [line for line in err.splitlines() if "nobody found" in line]
    assert len(said) == 1, err
    assert str(out) in said[0] and "not written" in said[0] and "--background" in said[0]
    assert "Traceback" not in err
    assert not out.exists()
