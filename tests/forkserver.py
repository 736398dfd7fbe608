"""`run` and `Popen` as in `subprocess`, for the tests' script runs: `python script.py ...` starts as a fork of a
server process that has already imported PyTorch (with `torch._dynamo`, which an optimizer's first step imports),
NumPy, Gymnasium, tyro and TensorBoard's writer, instead of a new interpreter that imports them again: about 4 s
less a process on a 2-core Zen 3, where the suite starts about 160 of them (docs/tests.md#timing).

The forked child is set up as `python script.py` would start: the script's folder first on `sys.path`, then
PYTHONPATH's; its argv, cwd, environment and stdin/stdout/stderr; Python's, NumPy's and torch's global generators
drawn anew; an exception or `sys.exit` ends it as it ends a script. Anything else runs as a new process, as
`subprocess` runs it: a command that is not `sys.executable script.py ...`, and an environment that differs from the
server's in a variable that the interpreter or a preloaded library reads as it starts (LOADED: OMP_NUM_THREADS,
MKL_ENABLE_INSTRUCTIONS, PYTHONHASHSEED, ...), which would not reach a library the server has loaded. MuJoCo and
dm_control are not preloaded: they pick their rendering backend from MUJOCO_GL when imported, which the scripts set
first.

What a forked run cannot show: a bug of a fresh interpreter only (a string hash order, an import a preloaded module
hides). The kill-and-resume tests run their uninterrupted run as a new process and the killed one forked, and
compare their numbers; FORKSERVER=0 runs the whole suite without the server.

`python tests/forkserver.py FD` is the server: it serves the socket FD of the test process that started it, and ends
when that process closes it."""

import io
import json
import os
import select
import signal
import socket
import subprocess
import sys
import time

PRELOADED = (
    "numpy",
    "torch",
    "torch._dynamo",
    "torch.optim.lr_scheduler",
    "torch.utils.tensorboard",
    "gymnasium",
    "tyro",
    "tqdm",
)
# the variables read as the interpreter, PyTorch, OpenMP, oneMKL, OpenBLAS or CUDA start, by prefix: a child whose
# environment differs from the server's in one runs as a new process (the others are read after the fork, from the
# child's os.environ)
LOADED = ("PYTHON", "OMP_", "KMP_", "GOMP_", "MKL_", "OPENBLAS_", "ATEN_", "TORCH", "PYTORCH_", "CUDA_", "NVIDIA_", "LD_")
LOADED += ("DNNL_", "ONEDNN_", "MALLOC_", "GLIBC_", "LC_", "LANG", "TQDM_", "NPY_", "NUMPY_")
SET_IN_THE_CHILD = {"PYTHONUNBUFFERED", "PYTHONPATH"}  # of those, the ones a child takes as a new interpreter would
MESSAGE = 1 << 20  # the largest request: an argv and an environment


# ---- the server --------------------------------------------------------------------------------------------------
def serve(fd: int):
    """Forks a child for each request on the socket; returns in the child only, with its request. Sends the client
    {"started": pid} for each fork and {"exited": pid, "status": waitstatus} as each child ends."""
    connection = socket.socket(fileno=fd)
    wake_read, wake_write = os.pipe()
    os.set_blocking(wake_write, False)
    signal.signal(signal.SIGCHLD, lambda *_: None)  # a handler, so that the wakeup fd is written
    signal.set_wakeup_fd(wake_write)
    while True:
        readable, _, _ = select.select([connection, wake_read], [], [])
        if wake_read in readable:
            os.read(wake_read, 4096)
        while True:  # reap every child that has ended
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                break
            if pid == 0:
                break
            connection.send(json.dumps({"exited": pid, "status": status}).encode())
        if connection in readable:
            data, fds, _, _ = socket.recv_fds(connection, MESSAGE, 3)
            if not data:  # the test process is gone
                os._exit(0)
            request = json.loads(data)
            pid = os.fork()
            if pid == 0:
                signal.set_wakeup_fd(-1)
                signal.signal(signal.SIGCHLD, signal.SIG_DFL)
                connection.close(), os.close(wake_read), os.close(wake_write)
                return request, fds
            for received in fds:
                os.close(received)
            connection.send(json.dumps({"started": pid, "id": request["id"]}).encode())


def become(request: dict, fds: list) -> str:
    """Sets up this forked child as `python script.py` would start; returns the script's path."""
    import random
    import tempfile

    import numpy as np
    import torch

    for target, received in zip((0, 1, 2), fds):
        os.dup2(received, target)
    for received in set(fds):
        os.close(received)
    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    script, *argv = request["argv"][1:]
    sys.argv = [script, *argv]
    sys.path[:] = [os.path.dirname(os.path.realpath(script)), *python_path(request["env"]), *BASE_PATH]
    unbuffered = bool(request["env"].get("PYTHONUNBUFFERED"))
    encoding, errors = sys.stdout.encoding, sys.stdout.errors
    sys.stdout = sys.__stdout__ = io.TextIOWrapper(
        io.FileIO(1, "w", closefd=False) if unbuffered else io.BufferedWriter(io.FileIO(1, "w", closefd=False)),
        encoding=encoding,
        errors=errors,
        line_buffering=os.isatty(1),
        write_through=unbuffered,
    )
    sys.stderr = sys.__stderr__ = io.TextIOWrapper(
        io.FileIO(2, "w", closefd=False) if unbuffered else io.BufferedWriter(io.FileIO(2, "w", closefd=False)),
        encoding=encoding,
        errors="backslashreplace",
        line_buffering=True,
        write_through=unbuffered,
    )
    random.seed()  # a new interpreter's generators start from the OS's entropy
    np.random.seed()
    torch.default_generator.seed()
    tempfile.tempdir = None  # found again from the child's TMPDIR
    return script


def python_path(env) -> list:
    """PYTHONPATH's entries as the interpreter puts them on sys.path: absolute, an empty one the working folder."""
    value = env.get("PYTHONPATH", "")
    return [os.path.abspath(p) for p in value.split(os.pathsep)] if value else []


# ---- the client (the tests' side) --------------------------------------------------------------------------------
class Server:
    """One server per test process, started at its first run; it ends when this process does."""

    def __init__(self):
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self.env = dict(os.environ)
        self.process = subprocess.Popen(
            [sys.executable, os.path.abspath(__file__), str(theirs.fileno())],
            pass_fds=[theirs.fileno()],
            stdin=subprocess.DEVNULL,
            env=self.env,
        )
        theirs.close()
        self.socket = ours
        self.exited = {}  # pid -> wait status, of the children that have ended
        self.requests = 0

    def serves(self, command, env) -> bool:
        if len(command) < 2 or command[0] != sys.executable or not str(command[1]).endswith(".py"):
            return False
        return self.process.poll() is None and loaded(env) == loaded(self.env)

    def receive(self, timeout=None):
        """Reads one message: an exit into self.exited (True), a start (its message); False if none came in time."""
        readable, _, _ = select.select([self.socket], [], [], timeout)
        if not readable:
            return False
        data = self.socket.recv(MESSAGE)
        if not data:
            raise ServerGone(f"the fork server ended (exit code {self.process.wait()})")
        message = json.loads(data)
        if "exited" in message:
            self.exited[message["exited"]] = message["status"]
            return True
        self.exited.pop(message["started"], None)  # an earlier child's status under a pid used again
        return message

    def start(self, command, cwd, env, fds) -> int:
        self.requests += 1
        request = {"argv": [str(c) for c in command], "cwd": os.path.abspath(cwd or os.getcwd()), "env": env}
        request["id"] = self.requests
        socket.send_fds(self.socket, [json.dumps(request).encode()], fds)
        while True:  # a start left unread by an interrupted request is passed over
            message = self.receive()
            if isinstance(message, dict) and message["id"] == request["id"]:
                return message["started"]


class ServerGone(RuntimeError):
    pass


def loaded(env) -> dict:
    """The variables of `env` that the interpreter or a preloaded library reads as it starts."""
    return {k: v for k, v in env.items() if k.startswith(LOADED) and k not in SET_IN_THE_CHILD}


_server = None


def server():
    """The server of this process's environment as it is now, started at the first call and again after a test changed
    a variable of LOADED in it (torch.compile sets TORCHINDUCTOR_CACHE_DIR; the earlier server ends with this process);
    None where it cannot run (FORKSERVER=0, or a system without SOCK_SEQPACKET sockets, such as macOS): every command
    then runs as a new process."""
    global _server
    if _server is None or (_server and loaded(_server.env) != loaded(os.environ)):
        try:
            _server = Server() if os.environ.get("FORKSERVER", "1") != "0" else False
        except OSError:
            _server = False
    return _server or None


def serves(command, env) -> bool:
    return server() is not None and server().serves(command, env)


class Forked:
    """The part of subprocess.Popen's interface the tests use, for a forked child."""

    def __init__(self, command, server, pid):
        self.args, self.server, self.pid, self.returncode = command, server, pid, None

    def poll(self):
        while self.returncode is None and self.pid not in self.server.exited and self.server.receive(0):
            pass
        if self.returncode is None and self.pid in self.server.exited:
            self.returncode = os.waitstatus_to_exitcode(self.server.exited.pop(self.pid))
        return self.returncode

    def wait(self, timeout=None):
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise subprocess.TimeoutExpired(self.args, timeout)
            self.server.receive(left)
        return self.returncode

    def send_signal(self, sig):
        if self.poll() is None:
            try:
                os.kill(self.pid, sig)
            except ProcessLookupError:  # it ended since
                pass

    def kill(self):
        self.send_signal(signal.SIGKILL)

    def terminate(self):
        self.send_signal(signal.SIGTERM)


def Popen(command, *, cwd=None, env=None, stdin=None, stdout=None, stderr=None, fresh=False):
    """subprocess.Popen(command, cwd=..., env=..., stdout=..., stderr=...), forked where the server can (fresh=True:
    never). stdout/stderr: None, a file, a file descriptor, subprocess.DEVNULL, or stderr=subprocess.STDOUT."""
    global _server
    env = dict(os.environ if env is None else env)
    if fresh or not serves(command, env):
        return subprocess.Popen(command, cwd=cwd, env=env, stdin=stdin, stdout=stdout, stderr=stderr)
    opened = []  # the /dev/null descriptors opened here for subprocess.DEVNULL (and for stdin by default)

    def fd(stream, default: int) -> int:
        if stream == subprocess.DEVNULL:
            opened.append(os.open(os.devnull, os.O_RDWR))
            return opened[-1]
        return default if stream is None else stream if isinstance(stream, int) else stream.fileno()

    stdout_fd = fd(stdout, 1)
    fds = [fd(subprocess.DEVNULL if stdin is None else stdin, 0), stdout_fd]
    fds.append(stdout_fd if stderr == subprocess.STDOUT else fd(stderr, 2))
    try:
        return Forked(command, server(), server().start(command, cwd, env, fds))
    except ServerGone:  # it ended (an import of PRELOADED failed, say): a new process, and none forked from now on
        _server = False
        return subprocess.Popen(command, cwd=cwd, env=env, stdin=stdin, stdout=stdout, stderr=stderr)
    finally:
        for descriptor in opened:
            os.close(descriptor)


def run(command, *, cwd=None, env=None, capture_output=False, text=False, timeout=None, fresh=False):
    """subprocess.run(command, cwd=..., env=..., capture_output=..., text=..., timeout=...), forked where the server
    can (fresh=True: never)."""
    env = dict(os.environ if env is None else env)
    if fresh or not serves(command, env):
        return subprocess.run(command, cwd=cwd, env=env, capture_output=capture_output, text=text, timeout=timeout)
    import tempfile

    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        process = Popen(
            command, cwd=cwd, env=env, stdout=out if capture_output else None, stderr=err if capture_output else None
        )
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
            raise
        captured = []
        for stream in (out, err):
            stream.seek(0)
            data = stream.read()
            captured.append(io.TextIOWrapper(io.BytesIO(data)).read() if text else data)  # as subprocess decodes
    return subprocess.CompletedProcess(command, process.returncode, *(captured if capture_output else (None, None)))


if __name__ == "__main__":
    import importlib

    fd = int(sys.argv[1])
    # what a child's sys.path has past its script's folder and its PYTHONPATH
    BASE_PATH = [p for p in sys.path[1:] if p not in python_path(os.environ)]
    for name in PRELOADED:
        importlib.import_module(name)
    request, fds = serve(fd)
    import runpy

    runpy.run_path(become(request, fds), run_name="__main__")
