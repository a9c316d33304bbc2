"""The preloaded runner (tests/preloaded_runner.py): a command forked from it ends as the same command in a new
interpreter does. A small console script of its own stands in for the heavy ones."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from preloaded_runner import PER_RUN_ENV, PreloadedScripts

SCRIPT = f"""#!{sys.executable}
import atexit, os, random, sys, threading, time, warnings
warnings.warn("said while importing")
print("printed while importing")


def main():
    mode = sys.argv[1]
    print("argv", sys.argv[1:], "cwd", os.getcwd(), "home", os.environ.get("HOME"), "umask", oct(os.umask(0)))
    print("to stderr", file=sys.stderr)
    os.write(2, b"straight to file descriptor 2\\n")
    warnings.warn("said while running")
    if mode == "none":
        return None
    if mode == "code":
        return 3
    if mode == "text":
        return "a message instead of a code"
    if mode == "raise":
        raise ValueError("uncaught")
    if mode == "later":
        atexit.register(print, "said at exit")
        threading.Thread(target=lambda: (time.sleep(0.2), print("said by a thread after main"))).start()
        return 0
    if mode == "random":
        print(random.random())
        return 0
    if mode == "fds":
        print("open file descriptors", sorted(int(fd) for fd in os.listdir("/proc/self/fd")))
        return 0
    if mode == "env":
        print(os.environ.get("PRELOADED_RUNNER_TEST"))
        return 0
    if mode == "sleep":
        time.sleep(60)
    if mode == "capabilities":
        print("".join(line for line in open("/proc/self/status") if line.startswith("Cap")), end="")
        for path in sys.argv[2:]:
            try:
                open(path).close()
                print("opened", path)
            except OSError as error:
                print("cannot open", path, error.errno)
        return 0
    return 0


if __name__ == '__main__':
    sys.exit(main())
"""


@pytest.fixture
def script(tmp_path) -> Path:
    path = tmp_path / "bin" / "probe"
    path.parent.mkdir()
    path.write_text(SCRIPT)
    path.chmod(0o755)
    return path


@pytest.fixture
def scripts(tmp_path):
    preloaded = PreloadedScripts(tmp_path / "runners")
    yield preloaded
    preloaded.close()


def env_for(home: Path) -> dict:
    home.mkdir(exist_ok=True)
    return dict(os.environ, HOME=str(home), XDG_CACHE_HOME=str(home / ".cache"), MPLCONFIGDIR=str(home / "mpl"))


def both(scripts: PreloadedScripts, argv, env, cwd):
    forked = scripts.run(argv, env, cwd, timeout=60)
    assert forked is not None, scripts.declined
    fresh = subprocess.run(argv, env=env, cwd=cwd, capture_output=True, text=True, timeout=60, check=False)
    return forked, fresh


@pytest.mark.parametrize("mode", ["none", "code", "text", "later", "fds"])
def test_a_forked_command_prints_and_ends_as_in_a_new_interpreter(mode, script, scripts, tmp_path):
    forked, fresh = both(scripts, [str(script), mode, "more args"], env_for(tmp_path / "home"), tmp_path)
    assert (forked.returncode, forked.stdout, forked.stderr) == (fresh.returncode, fresh.stdout, fresh.stderr)
    assert "said while importing" in forked.stderr and "printed while importing" in forked.stdout


def test_an_uncaught_exception_is_printed_with_its_traceback_and_ends_in_status_1(script, scripts, tmp_path):
    forked, fresh = both(scripts, [str(script), "raise"], env_for(tmp_path / "home"), tmp_path)
    assert forked.returncode == fresh.returncode == 1
    assert forked.stdout == fresh.stdout
    # the traceback's frames differ (the runner's below the script's); its start and its last line do not
    assert "Traceback (most recent call last):" in forked.stderr
    assert forked.stderr.splitlines()[-1] == fresh.stderr.splitlines()[-1] == "ValueError: uncaught"


def test_each_command_takes_its_home_folder_and_umask_and_draws_new_random_numbers(script, scripts, tmp_path):
    first = scripts.run([str(script), "random"], env_for(tmp_path / "one"), tmp_path, timeout=60)
    previous = os.umask(0o077)
    try:
        second = scripts.run([str(script), "random"], env_for(tmp_path / "two"), tmp_path / "two", timeout=60)
    finally:
        os.umask(previous)
    assert first is not None and second is not None
    assert f"home {tmp_path / 'one'} umask 0o22" in first.stdout.replace(f"cwd {tmp_path} ", "")
    assert f"cwd {tmp_path / 'two'} home {tmp_path / 'two'} umask 0o77" in second.stdout
    assert first.stdout.splitlines()[-1] != second.stdout.splitlines()[-1]
    assert scripts.starts == 1


def test_a_changed_environment_starts_the_runner_again(script, scripts, tmp_path):
    env = env_for(tmp_path / "home")
    assert scripts.run([str(script), "env"], env, tmp_path, timeout=60).stdout.splitlines()[-1] == "None"
    changed = dict(env, PRELOADED_RUNNER_TEST="set")
    assert scripts.run([str(script), "env"], changed, tmp_path, timeout=60).stdout.splitlines()[-1] == "set"
    assert scripts.starts == 2 and not scripts.declined
    assert "HOME" in PER_RUN_ENV  # a per-run variable alone starts nothing
    scripts.run([str(script), "env"], env_for(tmp_path / "other"), tmp_path, timeout=60)
    assert scripts.starts == 3  # back to the environment without PRELOADED_RUNNER_TEST


def test_a_command_past_its_timeout_is_killed(script, scripts, tmp_path):
    with pytest.raises(subprocess.TimeoutExpired) as expired:
        scripts.run([str(script), "sleep"], env_for(tmp_path / "home"), tmp_path, timeout=2)
    assert "argv ['sleep']" in expired.value.output
    after = scripts.run([str(script), "none"], env_for(tmp_path / "home"), tmp_path, timeout=60)
    assert after is not None and after.returncode == 0  # the runner serves on


def test_a_file_that_is_no_console_script_is_left_to_a_new_interpreter(scripts, tmp_path):
    assert scripts.run(["/bin/true"], env_for(tmp_path / "home"), tmp_path, timeout=60) is None
    assert scripts.declined == [("/bin/true", "/bin/true is not a console script")]


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("setpriv") is None, reason="needs root and setpriv")
def test_dropped_capabilities_are_those_setpriv_leaves(script, scripts, tmp_path):
    locked = tmp_path / "locked.txt"
    locked.write_text("secret")
    locked.chmod(0o000)
    argv = [str(script), "capabilities", str(locked)]
    env = env_for(tmp_path / "home")
    forked = scripts.run(argv, env, tmp_path, timeout=60, drop_capabilities=[1, 2, 3])
    assert forked is not None, scripts.declined
    setpriv = ["setpriv", "--bounding-set", "-dac_override,-dac_read_search,-fowner", "--"]
    fresh = subprocess.run(setpriv + argv, env=env, cwd=tmp_path, capture_output=True, text=True, check=False)
    assert forked.stdout == fresh.stdout and forked.returncode == fresh.returncode == 0
    assert f"cannot open {locked} 13" in forked.stdout
    kept = scripts.run(argv, env, tmp_path, timeout=60)
    assert kept is not None and f"opened {locked}" in kept.stdout  # the runner itself keeps them
