"""Console scripts run in processes forked from one that has already imported what the script imports: a command's
start-up (seconds of importing torch and nerfstudio) is paid once per script instead of once per run.

``python preloaded_runner.py SCRIPT REQUESTS RESPONSES`` (the runner) executes SCRIPT, a console script as pip
writes it (its imports, then its main under ``if __name__ == '__main__'``), under a name other than ``__main__``:
the imports run, the main does not. What the imports print is kept. Then, for each request read from the file
descriptor REQUESTS, it forks. The child takes the request's per-run environment variables (:data:`PER_RUN_ENV`;
the rest of its environment is the runner's, with whatever the imports set in it), working folder, umask and argv,
and optionally drops capabilities as ``setpriv`` would have; it gets pipes as its file descriptors 1 and 2, with
what the imports printed written to them first, draws new seeds for the ``random`` and ``numpy.random`` global
generators (a new interpreter seeds them from the OS), and runs SCRIPT as ``__main__``, as ``python SCRIPT
ARGS...`` would once its imports are done. The interpreter's own ending gives the exit status: ``SystemExit``,
or an uncaught exception printed by ``sys.excepthook`` (the command's, when it installs one) with status 1, then
thread joins, atexit handlers, the flush of stdout and stderr and the collection of what is left. The runner
reads both pipes until they close and the child has exited, kills the child once the request's timeout has
passed, and writes the exit status and both outputs to RESPONSES.

So the child is the process ``python SCRIPT ARGS...`` would be after its imports, but for what differs between
the runner's imports and a new process's: the per-run environment variables (the runner's imports see a home
folder of their own, new and empty as each command's is, and refuse to fork if they set or copied one of them),
the folder and argv (the test side makes both alike: an empty home folder, the script alone), Python's string
hash seed (one per runner) and the process ids. The objects the imports made are frozen (``gc.freeze``) before
each fork, so that the child's garbage collections skip them, as Python's documentation advises for a process that
forks without exec: like a new process's, they live to its end. A runner forks only while it runs no Python thread
but its main one and has not initialised CUDA; the OpenBLAS worker threads numpy starts at import stop before a
fork (OpenBLAS's fork handler) and start again when needed.

The test side, :class:`PreloadedScripts`, starts a runner per script (in the background) and sends it requests;
:meth:`PreloadedScripts.run` returns what ``subprocess.run(..., capture_output=True, text=True)`` would. This
module uses only the standard library: the runner imports nothing else before the script does.
"""

from __future__ import annotations

import gc
import io
import json
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List, Mapping, Optional, Sequence, Tuple

RUNNER = Path(__file__).resolve()
# Environment variables that may differ between a command and its runner. The home folder is each command's own
# (the bad-input catalogue gives every case one), and the imports read it (matplotlib's and torch's cache folders,
# fsspec's configuration): the runner's imports see a fresh empty one of its own, as each command's would. pytest
# sets PYTEST_CURRENT_TEST for each test; the scripts' imports read it only among all variables, looking for
# their own prefixes (tqdm, fsspec, networkx).
PER_RUN_ENV = ("HOME", "XDG_CACHE_HOME", "MPLCONFIGDIR", "PYTEST_CURRENT_TEST")
# a runner that has not answered by then is stuck (its imports take seconds)
START_TIMEOUT_S = 600.0


# ------------------------------------------------------------------ the messages between the two sides
class Channel:
    """Messages over a pair of pipes: a JSON line, then the byte strings its ``sizes`` list counts."""

    def __init__(self, read_fd: Optional[int], write_fd: Optional[int]):
        self.read_fd = read_fd
        self.write_fd = write_fd
        self._pending = bytearray()

    def send(self, header: dict, *blobs: bytes) -> None:
        assert self.write_fd is not None
        data = memoryview(
            json.dumps({**header, "sizes": [len(blob) for blob in blobs]}).encode() + b"\n" + b"".join(blobs)
        )
        while data:
            data = data[os.write(self.write_fd, data) :]

    def receive(self, deadline: Optional[float] = None) -> Optional[Tuple[dict, List[bytes]]]:
        """The next message; None when the other side has closed its end. TimeoutError past ``deadline``."""
        while b"\n" not in self._pending:
            if not self._fill(deadline):
                return None
        line, _, rest = bytes(self._pending).partition(b"\n")
        self._pending = bytearray(rest)
        header = json.loads(line)
        blobs = []
        for size in header["sizes"]:
            while len(self._pending) < size:
                if not self._fill(deadline):
                    raise EOFError("the message was cut short")
            blobs.append(bytes(self._pending[:size]))
            del self._pending[:size]
        return header, blobs

    def _fill(self, deadline: Optional[float]) -> bool:
        assert self.read_fd is not None
        if deadline is not None:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self.read_fd], [], [], left)[0]:
                raise TimeoutError("no answer from the preloaded runner")
        chunk = os.read(self.read_fd, 1 << 16)
        self._pending += chunk
        return bool(chunk)


# ------------------------------------------------------------------ the runner
class _Script:
    """A console script split as Python runs it: the statements before its final ``if __name__ == '__main__':``
    (its imports) and that block (its main), run in one ``__main__`` module."""

    def __init__(self, path: str):
        import ast
        import importlib.machinery
        import types

        with open(path, "rb") as handle:
            tree = ast.parse(handle.read(), path)
        if not tree.body or not _is_main_guard(tree.body[-1]):
            raise ValueError(f"{path} does not end in its main under if __name__ == '__main__':")
        self.imports = compile(ast.Module(body=tree.body[:-1], type_ignores=[]), path, "exec")
        self.main = compile(ast.Module(body=tree.body[-1:], type_ignores=[]), path, "exec")
        self.module = types.ModuleType("__main__")
        self.module.__dict__.update(
            __file__=path,
            __cached__=None,
            __builtins__=__builtins__,
            __loader__=importlib.machinery.SourceFileLoader("__main__", path),
        )


def _is_main_guard(node: object) -> bool:
    import ast

    if not isinstance(node, ast.If) or not isinstance(node.test, ast.Compare):
        return False
    test = node.test
    return (
        isinstance(test.left, ast.Name)
        and test.left.id == "__name__"
        and len(test.ops) == 1
        and isinstance(test.ops[0], ast.Eq)
        and isinstance(test.comparators[0], ast.Constant)
        and test.comparators[0].value == "__main__"
    )


def _preload(script: _Script) -> Tuple[bytes, bytes]:
    """Run the script's imports as ``python SCRIPT`` does before its main; what they printed on stdout and
    stderr."""
    path = script.module.__file__
    assert path is not None
    # sys.path[0] is the script's folder, as ``python SCRIPT`` makes it (symbolic links resolved), and the
    # script is __main__ while it imports
    sys.path[0] = os.path.dirname(os.path.realpath(path))
    sys.argv = [path]
    sys.modules["__main__"] = script.module
    saved = os.dup(1), os.dup(2)
    captured = os.memfd_create("stdout"), os.memfd_create("stderr")
    try:
        os.dup2(captured[0], 1)
        os.dup2(captured[1], 2)
        exec(script.imports, script.module.__dict__)
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        for fd, saved_fd in ((1, saved[0]), (2, saved[1])):
            os.dup2(saved_fd, fd)
            os.close(saved_fd)
    printed = []
    for fd in captured:
        os.lseek(fd, 0, os.SEEK_SET)
        chunks = []
        while chunk := os.read(fd, 1 << 16):
            chunks.append(chunk)
        printed.append(b"".join(chunks))
        os.close(fd)
    return printed[0], printed[1]


def _not_forkable(env_before: Mapping[str, str]) -> Optional[str]:
    """Why a fork of this process (its imports done, under ``env_before``) cannot stand in for a new one."""
    import threading

    if threading.active_count() != 1:
        return f"{threading.active_count()} Python threads run after the imports"
    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_initialized():
        return "the imports initialised CUDA, which a forked child cannot use"
    # A child keeps what the imports did to the environment (as a new process would have it after its own
    # imports) and takes the per-run variables of its command: that holds only if the imports left those alone
    # and set nothing from them.
    home = env_before.get("HOME", "")
    changed = sorted(key for key in set(env_before) | set(os.environ) if env_before.get(key) != os.environ.get(key))
    from_home = [key for key in changed if home and home in os.environ.get(key, "")]
    if set(changed) & set(PER_RUN_ENV) or from_home:
        return f"the imports set {sorted(set(changed) & set(PER_RUN_ENV)) + from_home} of the environment"
    return None


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


def capabilities() -> Dict[str, int]:
    """This process's capability sets (``/proc/self/status``: Inh, Prm, Eff, Bnd, Amb) as bit masks."""
    with open("/proc/self/status") as status:
        return {line[3:6]: int(line.split()[1], 16) for line in status if line.startswith("Cap")}


def _drop_capabilities(numbers: Sequence[int]) -> None:
    """Leave this process as root is once ``setpriv --bounding-set -<cap>,... -- COMMAND`` has executed COMMAND:
    the capabilities ``numbers`` out of the bounding, permitted and effective sets (an execve by root makes the
    permitted and effective sets the inheritable set and the bounding set; :meth:`PreloadedScripts.run` forks
    for it only from a runner whose sets are already so), checked against ``/proc/self/status``."""
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    pr_capbset_drop = 24  # linux/prctl.h
    for number in numbers:
        if libc.prctl(pr_capbset_drop, number, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), f"prctl(PR_CAPBSET_DROP, {number})")

    class Header(ctypes.Structure):
        _fields_ = [("version", ctypes.c_uint32), ("pid", ctypes.c_int)]

    class Data(ctypes.Structure):
        _fields_ = [("effective", ctypes.c_uint32), ("permitted", ctypes.c_uint32), ("inheritable", ctypes.c_uint32)]

    header, data = Header(0x20080522, 0), (Data * 2)()  # _LINUX_CAPABILITY_VERSION_3: two 32-bit words per set
    if libc.capget(ctypes.byref(header), data) != 0:
        raise OSError(ctypes.get_errno(), "capget")
    for number in numbers:
        word, bit = divmod(number, 32)
        data[word].effective &= ~(1 << bit) & 0xFFFFFFFF
        data[word].permitted &= ~(1 << bit) & 0xFFFFFFFF
    if libc.capset(ctypes.byref(header), data) != 0:
        raise OSError(ctypes.get_errno(), "capset")
    sets = capabilities()
    after_exec = sets["Inh"] | sets["Bnd"]
    if any(sets["Bnd"] >> number & 1 for number in numbers) or not sets["Prm"] == sets["Eff"] == after_exec:
        raise RuntimeError(f"capabilities after the drop are not those after setpriv's execve: {sets}")


def _child(request: dict, printed: Tuple[bytes, bytes], close: Sequence[int], out_w: int, err_w: int) -> None:
    """In the forked child: become the command's process (everything but running the script)."""
    for fd in close:
        os.close(fd)
    for key in PER_RUN_ENV:  # the rest is the runner's, equal to the command's (PreloadedScripts.run)
        if key in request["env"]:
            os.environ[key] = request["env"][key]
        else:
            os.environ.pop(key, None)
    os.chdir(request["cwd"])
    os.umask(request["umask"])
    if request["drop_capabilities"]:
        _drop_capabilities(request["drop_capabilities"])
    os.dup2(out_w, 1)
    os.dup2(err_w, 2)
    os.close(out_w)
    os.close(err_w)
    _write_all(1, printed[0])
    _write_all(2, printed[1])
    if "random" in sys.modules:
        sys.modules["random"].seed()
    if "numpy.random" in sys.modules:
        sys.modules["numpy.random"].seed()
    sys.argv = list(request["argv"])


def _collect(pid: int, out_r: int, err_r: int, timeout: float) -> Tuple[int, bool, bytes, bytes]:
    """Read the child's stdout and stderr until both close and it has exited (as ``communicate`` does); kill it
    past ``timeout``. Its exit status (negative: the signal that ended it), whether it timed out, and the output."""
    pidfd = os.pidfd_open(pid)
    output: Dict[int, bytearray] = {out_r: bytearray(), err_r: bytearray()}
    open_fds = [out_r, err_r]
    status: Optional[int] = None
    timed_out = False
    deadline = time.monotonic() + timeout
    while open_fds or status is None:
        left = deadline - time.monotonic()
        if left <= 0:
            timed_out = True
            if status is None:  # not yet reaped: the pid is still the child's
                os.kill(pid, signal.SIGKILL)
            break
        waiting = open_fds + ([pidfd] if status is None else [])
        for fd in select.select(waiting, [], [], left)[0]:
            if fd == pidfd:
                status = os.waitpid(pid, 0)[1]
                continue
            chunk = os.read(fd, 1 << 16)
            if chunk:
                output[fd] += chunk
            else:
                open_fds.remove(fd)
    if status is None:
        status = os.waitpid(pid, 0)[1]
    for fd in open_fds:  # killed: what is already in the pipes (a process it started may hold them open)
        while select.select([fd], [], [], 0.5)[0] and (chunk := os.read(fd, 1 << 16)):
            output[fd] += chunk
    for fd in (pidfd, out_r, err_r):
        os.close(fd)
    return os.waitstatus_to_exitcode(status), timed_out, bytes(output[out_r]), bytes(output[err_r])


def serve(script: _Script, channel: Channel) -> bool:
    """The runner's loop. Returns True in a forked child only, set up to run the script's main; False in the
    runner, once the test side has closed its end."""
    env_before = dict(os.environ)
    try:
        printed = _preload(script)
    except BaseException:  # noqa: BLE001 - told to the test side, which then runs this script in subprocesses
        import traceback

        channel.send({"ready": False, "why": traceback.format_exc()})
        return False
    why = _not_forkable(env_before)
    channel.send({"ready": why is None, "why": why, "euid": os.geteuid(), "capabilities": capabilities()})
    if why is not None:
        return False
    while (message := channel.receive()) is not None:
        request = message[0]
        out_r, out_w = os.pipe()
        err_r, err_w = os.pipe()
        setup_r, setup_w = os.pipe()
        sys.stdout.flush()
        sys.stderr.flush()
        # What the imports made moves to the collector's permanent generation: a child's collections (and the
        # last one at its exit) then walk only what the command makes, instead of writing to every imported
        # object's page and so copying the whole preloaded heap (a refused ns-train run: 2.3 s -> 0.6 s)
        gc.freeze()
        pid = os.fork()
        if pid == 0:
            assert channel.read_fd is not None and channel.write_fd is not None
            try:
                _child(request, printed, (channel.read_fd, channel.write_fd, out_r, err_r, setup_r), out_w, err_w)
                os.close(setup_w)
            except BaseException:  # noqa: BLE001 - the runner reports it; the command never ran
                import traceback

                _write_all(setup_w, traceback.format_exc().encode())
                os._exit(1)
            return True
        for fd in (out_w, err_w, setup_w):
            os.close(fd)
        chunks = []
        while chunk := os.read(setup_r, 1 << 16):
            chunks.append(chunk)
        os.close(setup_r)
        returncode, timed_out, out, err = _collect(pid, out_r, err_r, request["timeout"])
        setup_error = b"".join(chunks).decode(errors="replace") or None
        channel.send({"returncode": returncode, "timed_out": timed_out, "setup_error": setup_error}, out, err)
    return False


# ------------------------------------------------------------------ the test side
def _script_interpreter(path: str) -> Optional[str]:
    """The Python interpreter of a console script as pip writes it (``#!<python>`` and its main under
    ``if __name__ == '__main__'``); None for any other file."""
    try:
        with open(path, "rb") as handle:
            text = handle.read(1 << 16)
    except OSError:
        return None
    first = text.partition(b"\n")[0]
    interpreter = first[2:].decode(errors="replace").strip()
    if not first.startswith(b"#!") or " " in interpreter or not os.path.basename(interpreter).startswith("python"):
        return None
    try:
        _Script(path)
    except (SyntaxError, ValueError):
        return None
    return interpreter if os.access(interpreter, os.X_OK) else None


def _text(data: bytes) -> str:
    """``data`` as ``subprocess.run(..., text=True)`` decodes a pipe's bytes (the locale's encoding, newlines
    translated)."""
    encoding = io.TextIOWrapper(io.BytesIO()).encoding
    return data.decode(encoding).replace("\r\n", "\n").replace("\r", "\n")


def _fixed(env: Mapping[str, str]) -> Dict[str, str]:
    """``env`` but for :data:`PER_RUN_ENV`: what a runner's imports ran under."""
    return {key: value for key, value in env.items() if key not in PER_RUN_ENV}


class _Runner:
    def __init__(self, script: str, interpreter: str, folder: Path, env: Mapping[str, str]):
        self.script = script
        self.env = _fixed(env)
        requests_r, requests_w = os.pipe()
        responses_r, responses_w = os.pipe()
        folder.mkdir(parents=True)
        self.log = folder / "runner.log"
        home = folder / "home"
        home.mkdir()
        runner_env = dict(
            env, HOME=str(home), XDG_CACHE_HOME=str(home / ".cache"), MPLCONFIGDIR=str(home / ".matplotlib")
        )
        with open(self.log, "wb") as log:
            self.process = subprocess.Popen(
                [interpreter, str(RUNNER), script, str(requests_r), str(responses_w)],
                pass_fds=(requests_r, responses_w),
                stdout=log,
                stderr=log,
                cwd=home,
                env=runner_env,
            )
        os.close(requests_r)
        os.close(responses_w)
        self.channel = Channel(responses_r, requests_w)
        self.ready: Optional[dict] = None

    def wait_ready(self) -> bool:
        if self.ready is None:
            message = self.channel.receive(time.monotonic() + START_TIMEOUT_S)
            if message is None:
                raise RuntimeError(f"the preloaded runner of {self.script} ended while starting: {self.log_tail()}")
            self.ready = message[0]
        return bool(self.ready["ready"])

    def can_drop(self, numbers: Sequence[int]) -> bool:
        """Whether a fork of this runner can be left as setpriv leaves root with ``numbers`` out of its bounding
        set: the runner is root whose permitted and effective sets are what an execve would give it (the
        inheritable and bounding sets), none of ``numbers`` inheritable and no ambient capabilities."""
        assert self.ready is not None
        sets = self.ready["capabilities"]
        mask = sum(1 << number for number in numbers)
        return (
            self.ready["euid"] == 0
            and sets["Prm"] == sets["Eff"] == sets["Inh"] | sets["Bnd"]
            and not sets["Inh"] & mask
            and not sets["Amb"]
        )

    def log_tail(self) -> str:
        return self.log.read_text(errors="replace")[-3000:]

    def close(self) -> None:
        for fd in (self.channel.write_fd, self.channel.read_fd):
            if fd is not None:
                os.close(fd)
        self.channel.write_fd = self.channel.read_fd = None
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


class PreloadedScripts:
    """A runner per console script, with its home variables pointing into ``folder``.

    A runner's imports run under the environment of the command that starts it (``start``, or the first ``run``
    of its script), and a fork of it stands in only for commands under that same environment (but for
    :data:`PER_RUN_ENV`). The tests' own process changes its environment as it imports and runs things (sklearn,
    open3d and torch's compiler set variables), and its commands inherit that: a command under an environment
    that has changed starts the runners again under it. ``starts`` counts the runners started; ``declined``
    lists each command :meth:`run` left to a new interpreter, and why."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.runners: Dict[str, _Runner] = {}
        self.starts = 0
        self.declined: List[Tuple[str, str]] = []

    def start(self, scripts: Sequence[str], env: Mapping[str, str]) -> None:
        """Start the runners of ``scripts`` under ``env`` (their imports run in the background), each unless it
        runs under that environment already."""
        for script in scripts:
            runner = self.runners.get(script)
            if runner is not None and runner.env == _fixed(env):
                continue
            interpreter = _script_interpreter(script)
            if interpreter is None:
                continue
            if runner is not None:
                runner.close()
            self.starts += 1
            folder = self.folder / f"{self.starts}-{Path(script).name}"
            self.runners[script] = _Runner(script, interpreter, folder, env)

    def run(
        self,
        argv: Sequence[str],
        env: Mapping[str, str],
        cwd: Path,
        timeout: float,
        drop_capabilities: Sequence[int] = (),
    ) -> Optional[subprocess.CompletedProcess]:
        """``subprocess.run(argv, env=env, cwd=cwd, timeout=timeout, capture_output=True, text=True)``, in a fork
        of the runner of ``argv[0]``; None when it cannot run there (not a console script, a runner that cannot
        fork).

        ``drop_capabilities`` (Linux capability numbers): run it as ``setpriv --bounding-set -<cap>,... --
        ARGV`` would, run as root; None where a fork cannot be left in that state (:meth:`_Runner.can_drop`)."""
        if argv[0] in self.runners and self.runners[argv[0]].env != _fixed(env):
            self.start(list(self.runners), env)  # all of them: the next commands of the others see the change too
        why = self._why_not(argv, env, drop_capabilities)
        if why is not None:
            self.declined.append((" ".join(argv), why))
            return None
        runner = self.runners[argv[0]]
        if not os.path.isdir(cwd):
            raise FileNotFoundError(f"no such folder: {cwd}")
        umask = os.umask(0o022)
        os.umask(umask)
        request = {
            "argv": list(argv),
            "env": {key: env[key] for key in PER_RUN_ENV if key in env},
            "cwd": str(cwd),
            "umask": umask,
            "timeout": timeout,
            "drop_capabilities": list(drop_capabilities),
        }
        runner.channel.send(request)
        message = runner.channel.receive(time.monotonic() + timeout + START_TIMEOUT_S)
        if message is None:
            raise RuntimeError(f"the preloaded runner of {argv[0]} ended: {runner.log_tail()}")
        (answer, (out, err)) = message
        if answer["setup_error"]:
            raise RuntimeError(f"the preloaded runner could not set up {list(argv)}: {answer['setup_error']}")
        stdout, stderr = _text(out), _text(err)
        if answer["timed_out"]:
            raise subprocess.TimeoutExpired(list(argv), timeout, stdout, stderr)
        return subprocess.CompletedProcess(list(argv), answer["returncode"], stdout, stderr)

    def _why_not(self, argv: Sequence[str], env: Mapping[str, str], drop_capabilities: Sequence[int]) -> Optional[str]:
        """Why ``argv`` cannot run in a fork of its runner; None when it can."""
        self.start([argv[0]], env)
        runner = self.runners.get(argv[0])
        if runner is None:
            return f"{argv[0]} is not a console script"
        if not runner.wait_ready():
            assert runner.ready is not None
            return f"its runner cannot fork: {runner.ready['why']}"
        if drop_capabilities and not runner.can_drop(drop_capabilities):
            return f"a fork of its runner cannot be left without capabilities {list(drop_capabilities)} as setpriv leaves it"
        return None

    def close(self) -> None:
        for runner in self.runners.values():
            runner.close()
        self.runners.clear()


if __name__ == "__main__":
    _script = _Script(sys.argv[1])
    if serve(_script, Channel(int(sys.argv[2]), int(sys.argv[3]))):
        # a forked child: the script's main, as ``python SCRIPT ARGS...`` runs it once its imports are done; what
        # it raises ends this interpreter as it would end that one
        exec(_script.main, _script.module.__dict__)
    else:
        # the runner, its test side gone: what its imports registered to run at exit runs, then it ends without
        # the seconds of tearing down the modules it imported (it ran no command; its children are gone)
        import atexit

        atexit._run_exitfuncs()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
