"""Every command's wrapper (``cli_entry``): a user error, a missing file and Ctrl-C each end in one line
on stderr and their exit code, never a traceback; anything else is a bug and propagates. And
``atomic_path``: the destination is written whole or not at all."""

from __future__ import annotations

import pytest

from virgi_ns.errors import EXIT_USER_ERROR, InputError, atomic_path, cli_entry


def _exit(main, capsys) -> tuple[int, str]:
    with pytest.raises(SystemExit) as e:
        cli_entry(main)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return e.value.code, err.strip()


def _raise(exc: BaseException):
    def main():
        raise exc

    return main


def test_a_user_error_is_one_line_and_exit_2(capsys):
    assert _exit(_raise(InputError("scene.ply is truncated")), capsys) == (EXIT_USER_ERROR, "error: scene.ply is truncated")


def test_a_missing_file_is_one_line_and_exit_2(tmp_path, capsys):
    missing = tmp_path / "nope.ply"

    def main():
        open(missing, "rb")

    assert _exit(main, capsys) == (EXIT_USER_ERROR, f"error: no such file: {missing}")


def test_ctrl_c_is_one_line_and_exit_130(capsys):
    try:
        got = _exit(_raise(KeyboardInterrupt()), capsys)
    except KeyboardInterrupt:  # (left to propagate it would stop the whole test run)
        pytest.fail("Ctrl-C escaped cli_entry with a traceback")
    assert got == (130, "interrupted")


def test_a_bug_is_not_hidden(capsys):
    with pytest.raises(ZeroDivisionError):
        cli_entry(lambda: 1 / 0)
    cli_entry(lambda: None)  # a command that returns exits normally
    assert capsys.readouterr().err == ""


def test_atomic_path_writes_whole_or_not_at_all(tmp_path):
    dest = tmp_path / "sub" / "out.ply"
    with atomic_path(dest) as tmp:
        assert tmp.parent == dest.parent and tmp != dest
        tmp.write_bytes(b"first")
        assert not dest.exists()
    assert dest.read_bytes() == b"first"
    with pytest.raises(RuntimeError):
        with atomic_path(dest) as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("failed half way")
    assert dest.read_bytes() == b"first"  # the old file is kept
    assert sorted(p.name for p in dest.parent.iterdir()) == ["out.ply"]  # no temporary left
