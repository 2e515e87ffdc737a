import pytest

from rmavatar.utils import UserError, atomic_dir, atomic_path


def test_atomic_path_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_atomic_path_renames_on_success(tmp_path):
    target = tmp_path / "out.mp4"
    with atomic_path(target) as tmp:
        assert tmp.suffix == ".mp4" and tmp.parent == tmp_path
        tmp.write_text("done")
    assert target.read_text() == "done"
    assert [p.name for p in tmp_path.iterdir()] == ["out.mp4"]


def test_atomic_path_missing_folder_is_a_clear_error(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        with atomic_path(tmp_path / "nope" / "x.png"):
            pass


def test_atomic_dir(tmp_path):
    target = tmp_path / "data"
    with pytest.raises(ValueError):
        with atomic_dir(target) as tmp:
            (tmp / "a").write_text("x")
            raise ValueError
    assert not target.exists() and list(tmp_path.iterdir()) == []
    with atomic_dir(target) as tmp:
        (tmp / "a").write_text("x")
    assert (target / "a").read_text() == "x"


def test_atomic_outputs_follow_the_umask(tmp_path):
    import os

    old = os.umask(0o022)
    try:
        with atomic_path(tmp_path / "f.bin") as tmp:
            tmp.write_bytes(b"x")
        with atomic_dir(tmp_path / "d"):
            pass
    finally:
        os.umask(old)
    assert (tmp_path / "f.bin").stat().st_mode & 0o777 == 0o644
    assert (tmp_path / "d").stat().st_mode & 0o777 == 0o755


# --- the user's text files (read_text_file, read_yaml_file, read_yaml) ------------------------------------
USER_FILE_CASES = [  # (bytes, text the UserError must hold)
    ("jobs: []\n".encode("utf-16"), "is UTF-16 (little-endian) text, not UTF-8: save it as UTF-8"),
    ("jobs: []\n".encode("utf-16-be"), "is UTF-16 (no byte-order mark) text"),
    ("\ufeffjobs: []\n".encode("utf-16-be"), "is UTF-16 (big-endian) text"),
    ("jobs: []\n".encode("utf-32"), "is UTF-32 (little-endian) text"),
    ("name: café\n".encode("latin-1"), "is not UTF-8 text (byte 0xe9 on line 1"),
    (b"PK\x03\x04\x00\x00\x14\x00", "is not a text file (it holds binary data"),
    (b"a: 1\nb: [1, 2\nc: 3\n", "is not valid YAML: line 3, column 2"),
    (b"a: 1\n  b: 2\n", "is not valid YAML: line 2, column 4: mapping values are not allowed here"),
    (b"a: 1\nb: x\x07y\n", "is not valid YAML: line 2, column 5: the character U+0007 is not allowed"),
    (b"a: 1\nb: {x: 1, x: 2}\n", "line 2, column 11: the key 'x' is given twice (first on line 2)"),
    (b"- 1\n- 2\n", "expected a mapping (key: value lines) at the top level, got a list"),
    (b"just some words", "at the top level, got a string ('just some words')"),
]


@pytest.mark.parametrize("data, needle", USER_FILE_CASES, ids=range(len(USER_FILE_CASES)))
def test_read_yaml_names_the_file_and_the_problem(tmp_path, data, needle):
    from rmavatar.utils.config import read_yaml

    path = tmp_path / "c.yaml"
    path.write_bytes(data)
    with pytest.raises(UserError) as info:
        read_yaml(path)
    assert str(info.value).startswith(f"config file {path}") and needle in str(info.value), str(info.value)


def test_read_yaml_accepts_utf8_with_a_bom_empty_files_and_merge_keys(tmp_path):
    from rmavatar.utils.config import read_yaml
    from rmavatar.utils.files import read_text_file, read_yaml_file

    (tmp_path / "bom.yaml").write_bytes("\ufeffname: café\n".encode())
    assert read_yaml(tmp_path / "bom.yaml") == {"name": "café"}
    assert read_text_file(tmp_path / "bom.yaml") == "name: café\n"
    (tmp_path / "empty.yaml").write_text("")
    assert read_yaml(tmp_path / "empty.yaml") == {}
    assert read_yaml_file(tmp_path / "empty.yaml", mapping=False) is None
    (tmp_path / "merge.yaml").write_text("base: &b {x: 1, y: 2}\nc:\n  <<: *b\n  x: 3\n")  # overriding a merged key
    assert read_yaml(tmp_path / "merge.yaml") == {"base": {"x": 1, "y": 2}, "c": {"x": 3, "y": 2}}
    assert read_yaml_file(tmp_path / "merge.yaml", "jobs file", mapping=False)["c"]["x"] == 3


def test_read_text_file_missing_folder_and_unreadable(tmp_path, monkeypatch):
    from pathlib import Path

    from rmavatar.utils.files import read_text_file

    with pytest.raises(UserError, match=r"^jobs file .*none.yaml does not exist$"):
        read_text_file(tmp_path / "none.yaml", "jobs file")
    with pytest.raises(UserError, match=r"^jobs file .* is a folder, not a file$"):
        read_text_file(tmp_path, "jobs file")

    def denied(self):
        raise PermissionError(13, "Permission denied")

    (tmp_path / "locked.yaml").write_text("a: 1\n")
    monkeypatch.setattr(Path, "read_bytes", denied)  # root reads any file: fake the refusal
    with pytest.raises(UserError, match=r"^cannot read config file .*locked.yaml: Permission denied$"):
        read_text_file(tmp_path / "locked.yaml", "config file")
