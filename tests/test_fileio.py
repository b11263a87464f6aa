"""The output guard (`fileio.refuse_overwrite`) and atomic writes, as units: every way two
names can be one file (the same name, another spelling of the path, a symbolic link, a hard
link), outputs named twice, and what must stay allowed."""

from __future__ import annotations

import os

import pytest

from mirage_cli import fileio
from mirage_cli.errors import EnvironmentFailure, InputError, OutputError
from mirage_cli.fileio import atomic_path, atomic_write, refuse_overwrite


@pytest.fixture
def files(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "in.csv").write_text("input\n")
    (tmp_path / "other.csv").write_text("other\n")
    (tmp_path / "sub").mkdir()
    return tmp_path


def _refused(outputs, inputs, *words):
    with pytest.raises(InputError) as e:
        refuse_overwrite(outputs, inputs)
    msg = str(e.value)
    for w in words:
        assert w in msg, (w, msg)
    return msg


def test_output_that_is_the_input_is_refused(files):
    msg = _refused({"-o": "in.csv"}, {"POSES": "in.csv"}, "-o in.csv", "POSES in.csv")
    assert "overwrite the input" in msg and "choose another output name" in msg
    assert msg == (
        "-o in.csv is the same file as POSES in.csv: it would overwrite the input; "
        "choose another output name"
    )


def test_another_spelling_of_the_same_path_is_refused(files):
    _refused({"-o": str(files / "in.csv")}, {"POSES": "in.csv"})
    _refused({"-o": "sub/../in.csv"}, {"POSES": "./in.csv"})


def test_a_symbolic_link_to_the_input_is_refused(files):
    (files / "link.csv").symlink_to(files / "in.csv")
    _refused({"-o": "link.csv"}, {"POSES": "in.csv"})
    _refused({"-o": "in.csv"}, {"POSES": "link.csv"})


def test_a_hard_link_of_the_input_is_refused(files):
    """Another name, another folder, no symbolic link: only the inode says it is the input
    (writing it would replace the input's content for every name it has)."""
    os.link(files / "in.csv", files / "sub" / "hard.csv")
    assert os.path.realpath("sub/hard.csv") != os.path.realpath("in.csv")
    _refused({"-o": "sub/hard.csv"}, {"POSES": "in.csv"}, "overwrite the input")
    _refused({"--summary": "in.csv"}, {"--truth": "sub/hard.csv"})


def test_an_output_named_twice_is_refused(files):
    msg = _refused({"-o": "new.csv", "--summary": "new.csv"}, {"POSES": "in.csv"})
    assert msg == (
        "--summary new.csv is the same file as -o new.csv: it would be written twice; "
        "choose another output name"
    )
    # not yet existing, spelt differently: still one file
    _refused({"-o": "new.csv", "--tum": str(files / "new.csv")}, {})
    # a list of outputs holding one twice
    _refused({"-o": ["a.csv", "b.csv", "a.csv"]}, {})


def test_inputs_and_outputs_in_lists(files):
    _refused({"-o": ["x.csv", "in.csv"]}, {"INPUT": ["other.csv", "in.csv"]}, "INPUT in.csv")
    _refused({"-o": ("in.csv",)}, {"INPUT": ("in.csv",)})


def test_distinct_files_are_allowed(files):
    refuse_overwrite({"-o": "new.csv", "--summary": "new.yaml"}, {"POSES": "in.csv"})
    refuse_overwrite({"-o": "other.csv"}, {"POSES": "in.csv"})  # an existing other file
    refuse_overwrite({"-o": "sub/in.csv"}, {"POSES": "in.csv"})  # same name, other folder
    # unset options (None, empty) are no paths
    refuse_overwrite({"-o": "new.csv", "--plot": None, "--tum": ""}, {"--truth": None})
    refuse_overwrite({"-o": ["a.csv", None, ""]}, {"INPUT": [None, "in.csv", ""]})
    refuse_overwrite({}, {"POSES": "in.csv"})
    refuse_overwrite({"-o": "in.csv"}, {})  # overwriting a file that is no input is fine
    # two inputs may be one file (reading twice destroys nothing)
    refuse_overwrite({"-o": "new.csv"}, {"POSES": "in.csv", "--truth": "in.csv"})


def test_paths_normalises_options():
    assert fileio._paths(None) == [] and fileio._paths("") == []
    assert fileio._paths("a") == ["a"]
    assert fileio._paths(["a", None, "", "b"]) == ["a", "b"]
    assert fileio._paths(("a",)) == ["a"]


def test_same_file(files):
    """The guard's notion of 'the same file': by real path and by inode (a hard link)."""
    os.link(files / "in.csv", files / "hard.csv")
    guard = fileio._Guard([fileio._Input.of("POSES", "in.csv")])
    assert guard.clash("hard.csv") is not None  # another name, the same inode
    assert guard.clash(str(files / "in.csv")) is not None
    assert guard.clash("./in.csv") is not None
    assert guard.clash("other.csv") is None
    assert guard.clash("new.csv") is None  # does not exist yet
    new = fileio._Guard([fileio._Input.of("POSES", "new.csv")])
    assert new.clash("./new.csv") is not None  # neither exists yet: by path
    assert new.clash("in.csv") is None


# --- atomic writes ------------------------------------------------------------------------
def test_atomic_write_replaces_only_on_success(files):
    target = files / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_write(target) as f:
        f.write("half")
        raise RuntimeError("failed mid-write")
    assert target.read_text() == "old"
    with atomic_write(target) as f:
        f.write("new")
    assert target.read_text() == "new"
    assert sorted(p.name for p in files.iterdir()) == ["in.csv", "other.csv", "out.txt", "sub"]
    assert not fileio._TEMPS


def test_atomic_path_keeps_the_extension_and_checks_the_result(files):
    target = files / "cam.yaml"
    target.write_text("old")
    with atomic_path(target) as tmp:
        assert tmp.parent == files and tmp.suffix == ".yaml" and tmp.name.startswith(".cam.yaml.")
        assert tmp in fileio._TEMPS
        tmp.write_text("x")
    assert target.read_text() == "x" and not fileio._TEMPS
    with pytest.raises(EnvironmentFailure, match="nothing was written"), atomic_path(target):
        pass  # an empty file is a failed write
    with pytest.raises(EnvironmentFailure, match="does not read back"):
        with atomic_path(target, verify=lambda p: False) as tmp:
            tmp.write_text("y")
    with pytest.raises(EnvironmentFailure, match="does not read back"):
        with atomic_path(target, verify=lambda p: 1 / 0) as tmp:
            tmp.write_text("y")
    assert target.read_text() == "x"
    assert sorted(p.name for p in files.iterdir()) == ["cam.yaml", "in.csv", "other.csv", "sub"]


def test_atomic_file_mode_follows_the_umask(files):
    old = os.umask(0o027)
    try:
        with atomic_write(files / "m.txt") as f:
            f.write("x")
    finally:
        os.umask(old)
    assert (files / "m.txt").stat().st_mode & 0o777 == 0o640


def test_check_writable(files):
    assert fileio.check_writable("new.csv").name == "new.csv"
    with pytest.raises(OutputError, match="is a directory"):
        fileio.check_writable("sub")
    with pytest.raises(OutputError, match="does not exist"):
        fileio.check_writable("nope/new.csv")


def test_cleanup_temps_removes_what_is_registered(files):
    t = fileio.register_temp(files / ".leftover")
    t.write_text("x")
    fileio.cleanup_temps()
    assert not t.exists() and not fileio._TEMPS
    fileio.cleanup_temps()  # idempotent
