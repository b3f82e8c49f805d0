"""A warm worker for the workflow's short jobs (local execution only).

Every rule runs ``python -m nemo COMMAND ...``: a new interpreter that spends about a second
importing numpy, scipy, pandas, pyarrow and trimesh before a step that often takes about as
long. When the workflow runs locally it starts one worker (``serve``) that has imported them
once; ``python -m nemo`` finds it through the environment variable :data:`ENV` (a Unix
socket) and asks it to fork a child that runs the command with the caller's arguments,
working directory, environment and standard streams (passed as file descriptors). The caller
waits for the child's exit status, forwards SIGINT/SIGTERM to it, and the child stops when
the caller goes away. Without a worker (cluster jobs, a user's shell) the command runs
in-process as before; a forked child computes exactly what a fresh process computes.

The standard library's ``multiprocessing.forkserver`` forks workers for one Python parent;
here the callers are separate processes started by Snakemake's shell commands, so the
request (argv, cwd, environment, descriptors) travels over a Unix socket instead.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import struct
import sys
import time

#: Environment variable naming the worker's socket ("off" or unset: no worker).
ENV = "NEMO_WORKER"
#: Modules imported once by the worker (the heavy ones every command needs).
PRELOAD = ("numpy", "scipy.ndimage", "scipy.sparse", "scipy.spatial", "pandas", "pyarrow.parquet",
           "trimesh", "skimage.measure", "skimage.filters", "tifffile", "zarr", "nemo.cli", "nemo.stages",
           "nemo.defects", "nemo.directors", "nemo.morphology", "nemo.order", "nemo.peel", "nemo.io",
           "nemo.surface", "nemo.summary", "nemo.track")


def _send(conn: socket.socket, obj: dict) -> None:
    data = json.dumps(obj).encode()
    conn.sendall(struct.pack("!I", len(data)) + data)


def _recv(conn: socket.socket) -> dict | None:
    head = _recv_exact(conn, 4)
    if head is None:
        return None
    body = _recv_exact(conn, struct.unpack("!I", head)[0])
    return None if body is None else json.loads(body)


def _recv_exact(conn: socket.socket, n: int) -> bytes | None:
    buf = b""
    while len(buf) < n:
        chunk = conn.recv(n - len(buf))
        if not chunk:
            return None
        buf += chunk
    return buf


# ----------------------------------------------------------------------------- client
def forward(argv: list[str]) -> int | None:
    """Run ``nemo argv`` in the worker named by :data:`ENV`; None when there is none to use."""
    path = os.environ.get(ENV)
    if not path or path == "off" or os.environ.get("SLURM_JOB_ID"):
        return None
    for _ in range(100):  # a worker still importing: its folder exists, the socket not yet
        if os.path.exists(path) or not os.path.isdir(os.path.dirname(path)):
            break
        time.sleep(0.05)
    if not os.path.exists(path):
        return None
    conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        conn.connect(path)
    except OSError:
        return None  # a worker that went away: run here
    request = json.dumps({"argv": argv, "cwd": os.getcwd(), "env": dict(os.environ)}).encode()
    try:
        socket.send_fds(conn, [struct.pack("!I", len(request)) + request], [0, 1, 2])
        reply = _recv(conn)
    except OSError:  # the worker stopped (e.g. NEMO's code changed) before starting the command
        reply = None
    if reply is None:
        return None  # refused before starting: run here
    pid = int(reply["pid"])

    def relay(signum, frame):  # noqa: ARG001
        try:
            os.kill(pid, signum)
        except ProcessLookupError:
            pass

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, relay)
    try:
        status = _recv(conn)
    except OSError:
        status = None
    if status is None:
        print(f"nemo: the worker's process {pid} ended without a status (killed?)", file=sys.stderr)
        return 1
    return int(status["status"])


# ----------------------------------------------------------------------------- server
def _child(conn: socket.socket) -> None:
    """In the forked child: take the request, become the caller, run the command."""
    msg, fds, _, _ = socket.recv_fds(conn, 1 << 20, 3)
    size = struct.unpack("!I", msg[:4])[0]
    while len(msg) < size + 4:
        msg += conn.recv(size + 4 - len(msg))
    request = json.loads(msg[4:])
    sys.stdout.flush()
    sys.stderr.flush()
    for target, fd in enumerate(fds):
        os.dup2(fd, target)
        os.close(fd)
    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    threads = os.environ.get("OMP_NUM_THREADS")
    if threads and threads.isdigit():
        from threadpoolctl import threadpool_limits

        threadpool_limits(int(threads))
    _send(conn, {"pid": os.getpid()})
    import threading

    def watch() -> None:  # the caller closes the connection only when it dies
        if _recv_exact(conn, 1) is None:
            os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, daemon=True).start()
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    from nemo.cli import main

    try:
        code = main(request["argv"])
    except SystemExit as exc:  # argparse's --help and usage errors
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    except BaseException:  # noqa: BLE001 - a bug: the traceback goes to the caller's stderr, as without a worker
        import traceback

        traceback.print_exc()
        code = 1
    sys.stdout.flush()
    sys.stderr.flush()
    _send(conn, {"status": int(code or 0)})


def _source_stamp() -> int:
    """A fingerprint of NEMO's own source files (names and modification times)."""
    root = os.path.dirname(os.path.abspath(__file__))
    return hash(tuple(sorted((os.path.join(d, f), os.stat(os.path.join(d, f)).st_mtime_ns)
                             for d, _, files in os.walk(root) for f in files if f.endswith(".py"))))


def serve(path: str, idle_timeout: float = 900.0, parent: int | None = None) -> None:
    """Listen on the Unix socket ``path`` and fork a child per request.

    Stops after ``idle_timeout`` seconds without a request, when process ``parent`` (the
    Snakemake run that started it) is gone, when its folder is removed (:func:`stop`), or when
    NEMO's source files change (the caller then runs the command itself, with the new code).
    """
    import importlib
    import select

    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:  # whatever happens, the socket and its folder go: callers then run commands themselves
        for name in PRELOAD:
            importlib.import_module(name)
        from nemo import config

        for section in ("mesh", "curvature", "thickness", "layer", "directors", "order", "defects", "tracking"):
            config.section(section, {"range": [0, 1]} if section == "layer" else None)  # schema read once
        import gc

        gc.freeze()  # the children's garbage collector leaves the imported objects (and their pages) alone
        stamp = _source_stamp()
        signal.signal(signal.SIGCHLD, signal.SIG_IGN)  # children are reaped by the kernel
        server.bind(path)
        server.listen(64)
        last = time.monotonic()
        while time.monotonic() - last < idle_timeout:
            if (parent is not None and not _alive(parent)) or not os.path.isdir(os.path.dirname(path)):
                break  # the run that started us is over, or stop() removed our folder
            if not select.select([server], [], [], 2.0)[0]:
                continue
            conn, _ = server.accept()
            if _source_stamp() != stamp:  # NEMO's code changed: never mix it with what we imported
                conn.close()  # the caller runs the command itself
                break
            last = time.monotonic()
            sys.stdout.flush()
            sys.stderr.flush()
            if os.fork() == 0:
                server.close()
                signal.signal(signal.SIGCHLD, signal.SIG_DFL)
                try:
                    _child(conn)
                finally:
                    os._exit(0)
            conn.close()
    finally:
        server.close()
        if os.path.exists(path):
            os.unlink(path)
        try:
            os.rmdir(os.path.dirname(path))
        except OSError:
            pass


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def start(idle_timeout: float = 900.0, wait: bool = True) -> str:
    """Start a worker in the background for this process; returns its socket path.

    The worker stops when this process ends (or after ``idle_timeout`` s without work). With
    ``wait=False`` it returns at once; callers wait for the socket while the folder exists.
    """
    import subprocess
    import tempfile

    folder = tempfile.mkdtemp(prefix="nemo-worker-")
    path = os.path.join(folder, "socket")
    subprocess.Popen(
        [sys.executable, "-m", "nemo.worker", path, str(idle_timeout), str(os.getpid())],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    if wait:
        for _ in range(300):  # the imports take about a second
            if os.path.exists(path):
                break
            time.sleep(0.05)
    return path


def stop(path: str) -> None:
    """Stop the worker at ``path`` (it exits within seconds; callers then run commands themselves)."""
    import shutil

    shutil.rmtree(os.path.dirname(path), ignore_errors=True)


if __name__ == "__main__":
    serve(sys.argv[1], float(sys.argv[2]), int(sys.argv[3]) if len(sys.argv) > 3 else None)
