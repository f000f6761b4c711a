"""Files written whole or not at all; exceptions on one line."""

import pytest

from mjxdiff.errors import one_line
from mjxdiff.files import atomic_write


def test_a_write_that_fails_leaves_the_old_file_whole_and_no_temporary(tmp_path):
    path = atomic_write(tmp_path / "sub" / "report.json", "old\n")
    assert path.read_text() == "old\n"

    def interrupted(tmp):
        tmp.write_text("half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        atomic_write(path, interrupted)
    assert path.read_text() == "old\n" and sorted(p.name for p in path.parent.iterdir()) == ["report.json"]
    assert atomic_write(path, b"\x00new").read_bytes() == b"\x00new"
    assert atomic_write(path, lambda tmp: tmp.write_text("by a writer")).read_text() == "by a writer"


def test_an_exception_is_one_line_with_its_type():
    assert one_line(ValueError("bad\n  model:\tline 3")) == "ValueError: bad model: line 3"
    assert one_line(RuntimeError("x" * 50), limit=20) == "RuntimeError: xxxxxx"
