"""Files written whole or not at all: an interrupted write leaves the previous file and no temporary one."""

import pytest

from dipnet.core.atomic_write import write_atomically


@pytest.mark.parametrize("binary", [False, True])
def test_a_write_replaces_the_file_whole(tmp_path, binary):
    path = tmp_path / "out.dat"
    path.write_text("old")
    data = b"new contents" if binary else "new contents"
    assert write_atomically(path, lambda stream: stream.write(data), binary=binary) == path
    assert path.read_text() == "new contents" and sorted(p.name for p in tmp_path.iterdir()) == ["out.dat"]


def test_an_interrupted_write_leaves_the_previous_file_and_no_temporary_one(tmp_path):
    path = tmp_path / "out.yaml"
    path.write_text("previous: 1\n")

    def killed(stream):
        stream.write("half: ")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_atomically(path, killed)
    assert path.read_text() == "previous: 1\n" and sorted(p.name for p in tmp_path.iterdir()) == ["out.yaml"]
