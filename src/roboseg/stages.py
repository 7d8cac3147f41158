"""Stages of a long job (``make train``, ``make reproduce``): each a ``roboseg-*`` command or a
Python callable, run once, resumable, its output logged.

:class:`Stages` runs them (one at a time, or independent commands side by side);
:class:`Step` describes one; :func:`script` finds a command beside this interpreter.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import importlib
import importlib.metadata
import io
import logging
import math
import os
import platform
import shlex
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, NoReturn

log = logging.getLogger(__name__)


def script(name: str) -> str:
    """The console script ``name`` beside this interpreter (the project's venv)."""
    candidate = Path(sys.executable).with_name(name)
    return str(candidate) if candidate.exists() else name


def machine_description() -> str:
    """``<CPU model>, <n> cores, <OS>`` of this machine."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{model}, {os.cpu_count()} logical cores, {platform.system()} {platform.release()}"


def today() -> str:
    """The local date and time, ISO format to the minute."""
    return _dt.datetime.now().isoformat(timespec="minutes")


@dataclass
class Step:
    """One stage: a command (``argv``, run in ``cwd``) or a Python callable (``fn``).

    A ``tolerant`` command that fails is recorded (exit status in its marker) and the run goes on:
    used where a failure is itself a result (a registration that does not converge, a bench).
    Consecutive ``parallel`` commands are independent and single-threaded: they run side by
    side, ``jobs`` at a time, each as its own process.
    """

    name: str
    argv: list[str] | None = None
    fn: Callable[[], None] | None = None
    tolerant: bool = False
    cwd: Path | None = None
    parallel: bool = False


def _pump(stream: IO[str], sinks: Sequence[IO[str]], lock: threading.Lock) -> None:
    for line in stream:
        with lock:
            for sink in sinks:
                sink.write(line)
                sink.flush()


class Stages:
    """Runs named stages once, with progress (``[k/N]``, elapsed minutes), each stage's output
    teed to the terminal and ``root/logs/<stage>.log``; tolerant and in-process stages.

    A finished stage leaves ``root/.<stage>.done`` (its seconds, exit status if not 0, start and
    end time); a stage whose marker exists is skipped, so an interrupted run resumes where it
    stopped (:meth:`redo_after_pending` clears the markers of what follows a stage to redo).
    ``runner="fork"`` runs a ``roboseg-*`` command in a forked child of this process (after
    :func:`preimport`: the same command without the interpreter's start-up cost, ~3 s a
    command); ``"process"`` runs every command as its own process.
    """

    def __init__(self, root: Path, total: int | None = None, runner: str = "fork") -> None:
        self.root = root
        self.root.mkdir(parents=True, exist_ok=True)
        if runner not in ("fork", "process") or (runner == "fork" and not hasattr(os, "fork")):
            runner = "process"
        self.runner = runner
        self.total = total
        self.count = 0
        self._count_lock = threading.Lock()
        self.t0 = time.perf_counter()
        self.logs = root / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)

    def marker(self, name: str) -> Path:
        """The file whose presence marks stage ``name`` as finished."""
        return self.root / f".{name}.done"

    def _prefix(self, index: int) -> str:
        minutes = (time.perf_counter() - self.t0) / 60
        of = "" if self.total is None else f"/{self.total}"
        return f"[{index}{of} {minutes:5.1f} min]"

    def status(self, name: str) -> tuple[float | None, int | None]:
        """``(seconds, exit status)`` from a stage's marker; ``(None, None)`` when not done."""
        marker = self.marker(name)
        if not marker.exists():
            return None, None
        lines = marker.read_text().splitlines()
        seconds = float(lines[0].split()[0]) if lines else None
        code = next((int(x.split()[-1]) for x in lines if x.startswith("exit status")), 0)
        return seconds, code

    def interval(self, name: str) -> tuple[float, float] | None:
        """``(start, end)`` (Unix time, s) of a finished stage, if its marker records it."""
        marker = self.marker(name)
        if not marker.exists():
            return None
        for line in marker.read_text().splitlines():
            if line.startswith("ran "):
                start, end = line.split()[1:3]
                return float(start), float(end)
        return None

    def _launch(
        self,
        argv: Sequence[str],
        cwd: Path | None,
        fn: Callable[[], Any] | None = None,
        process: bool = False,
    ) -> tuple[Callable[[], int], IO[str], IO[str]]:
        """Start a stage: ``(wait() -> exit status, stdout, stderr)``. With the fork runner a
        ``roboseg-*`` command (or ``fn``) runs in a forked child of this process, which has
        imported the libraries once (the same command, without its start-up cost); with
        ``process`` (stages running side by side: no fork from a threaded parent) the command
        runs as its own process."""
        if process and fn is not None:
            raise ValueError("a stage run as its own process must be a command, not a function")
        target = fn
        if target is None and self.runner == "fork" and cwd is None and not process:
            target = _entry_point(argv[0])
        if target is None:
            proc = subprocess.Popen(
                list(argv), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                cwd=cwd, bufsize=1, errors="replace",
            )
            assert proc.stdout is not None and proc.stderr is not None
            return proc.wait, proc.stdout, proc.stderr
        out_r, out_w = os.pipe()
        err_r, err_w = os.pipe()
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:  # child: never returns
            os.close(out_r)
            os.close(err_r)
            _run_child(target, list(argv), out_w, err_w)
        os.close(out_w)
        os.close(err_w)

        def wait() -> int:
            return os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])

        return wait, os.fdopen(out_r, errors="replace"), os.fdopen(err_r, errors="replace")

    def _execute(
        self,
        name: str,
        argv: Sequence[str],
        cwd: Path | None,
        fn: Callable[[], Any] | None,
        process: bool = False,
    ) -> int:
        """Run one stage, its output teed to the terminal and the stage's log files."""
        lock = threading.Lock()
        with (
            open(self.logs / f"{name}.log", "w") as full,
            open(self.logs / f"{name}.stdout", "w") as out,
        ):
            full.write(f"$ {shlex.join(argv)}\n# {today()} on {machine_description()}\n")
            full.flush()
            wait, stdout, stderr = self._launch(argv, cwd, fn, process)
            pumps = [
                threading.Thread(target=_pump, args=(stdout, [sys.stdout, full, out], lock)),
                threading.Thread(target=_pump, args=(stderr, [sys.stderr, full], lock)),
            ]
            for p in pumps:
                p.start()
            code = wait()
            for p in pumps:
                p.join()
            stdout.close()
            stderr.close()
        return code

    def run(
        self,
        name: str,
        argv: Sequence[str],
        *,
        tolerant: bool = False,
        cwd: Path | None = None,
        fn: Callable[[], Any] | None = None,
        process: bool = False,
    ) -> bool:
        """Run stage ``name`` (the command ``argv``, or ``fn`` in a child process) unless it
        already finished; a failure raises ``SystemExit`` unless ``tolerant`` (then it is
        recorded in the marker and the run goes on). ``process``: see :meth:`_launch`."""
        with self._count_lock:
            self.count += 1
            index = self.count  # this stage's number (others may start while it runs)
        if self.marker(name).exists():
            print(f"{self._prefix(index)} [{name}] done already, skipped", flush=True)
            return False
        shown = shlex.join(argv) if fn is None else "(in a child process)"
        print(f"{self._prefix(index)} [{name}] $ {shown}", flush=True)
        t0, started = time.perf_counter(), time.time()
        code = self._execute(name, argv, cwd, fn, process)
        seconds = time.perf_counter() - t0
        if code != 0 and not tolerant:
            raise SystemExit(
                f"[{name}] failed with exit status {code} (log: {self.logs / f'{name}.log'})"
            )
        self.marker(name).write_text(
            f"{seconds:.1f} s\n"
            + (f"exit status {code}\n" if code else "")
            + f"ran {started:.1f} {time.time():.1f}\n"
        )
        note = f", exit status {code} (recorded, continuing)" if code else ""
        print(f"{self._prefix(index)} [{name}] finished in {seconds:.0f} s{note}", flush=True)
        return True

    def redo_after_pending(self, groups: Sequence[Sequence[str]]) -> list[str]:
        """Remove the markers of every stage in the groups after the first group holding an
        unfinished stage, and return their names: a rerun redoes what follows a stage it runs
        (its inputs may change). ``groups``: stage names in plan order, stages that run side by
        side (independent of each other) sharing a group."""
        removed: list[str] = []
        pending = False
        for group in groups:
            if pending:
                for name in group:
                    if self.marker(name).exists():
                        self.marker(name).unlink()
                        removed.append(name)
            elif any(not self.marker(name).exists() for name in group):
                pending = True
        return removed

    def run_side_by_side(self, steps: Sequence[Step], jobs: int) -> int:
        """Run independent command ``steps`` (see :attr:`Step.parallel`) ``jobs`` at a time,
        each as its own process; returns how many ran. A failing non-tolerant one raises
        ``SystemExit`` once the others have finished."""
        def one(step: Step) -> bool:
            assert step.argv is not None, f"{step.name}: only commands run side by side"
            return self.run(
                step.name, step.argv, tolerant=step.tolerant, cwd=step.cwd, process=jobs > 1
            )

        if jobs <= 1 or len(steps) <= 1:
            return sum(one(s) for s in steps)
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            futures = [pool.submit(one, s) for s in steps]
        return sum(f.result() for f in futures)

    def wall_seconds(self, names: Sequence[str]) -> float:
        """Wall-clock time (s) covered by the recorded runs of stages ``names`` (the union of
        their intervals: stages side by side count once); stages without one add their
        duration."""
        spans, loose = [], 0.0
        for name in names:
            span = self.interval(name)
            if span is not None:
                spans.append(span)
            else:
                loose += self.status(name)[0] or 0.0
        total, end = 0.0, -math.inf
        for a, b in sorted(spans):
            if b > end:
                total += b - max(a, end)
                end = b
        return total + loose


def _entry_point(script: str) -> Callable[[], Any] | None:
    """The function behind the console script ``script`` (a path or a name), if installed."""
    name = Path(script).name
    for ep in importlib.metadata.entry_points(group="console_scripts", name=name):
        return ep.load()
    return None


def _run_child(target: Callable[[], Any], argv: list[str], out_fd: int, err_fd: int) -> NoReturn:
    """In a forked child: output to the given pipes, ``sys.argv = argv``, run, exit."""
    code = 0
    try:
        os.dup2(out_fd, 1)
        os.dup2(err_fd, 2)
        os.close(out_fd)
        os.close(err_fd)
        sys.stdout = sys.__stdout__ = io.TextIOWrapper(
            os.fdopen(1, "wb", closefd=False), line_buffering=True
        )
        sys.stderr = sys.__stderr__ = io.TextIOWrapper(
            os.fdopen(2, "wb", closefd=False), line_buffering=True
        )
        sys.argv = list(argv)
        from hydra.core.global_hydra import GlobalHydra

        GlobalHydra.instance().clear()  # this process's own Hydra run is not the child's
        target()
    except SystemExit as exc:
        if isinstance(exc.code, int):
            code = exc.code
        elif exc.code is not None:
            print(exc.code, file=sys.stderr)
            code = 1
    except BaseException:  # noqa: BLE001 - reported like an interpreter would, exit status 1
        traceback.print_exc()
        code = 1
    finally:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)


def preimport() -> None:
    """Import what the commands import, once, before forking them (no computation here: the
    forked children start from a process that has not started any thread pool)."""
    for module in ("roboseg.cli.simulate", "roboseg.cli.annotate", "roboseg.cli.train",
                   "roboseg.cli.evaluate", "roboseg.cli.register", "roboseg.cli.track",
                   "export.cli", "roboseg.training", "datamodules"):
        try:
            importlib.import_module(module)
        except ImportError as exc:  # the command then imports it itself, or reports it
            log.debug("pre-import of %s failed: %s", module, exc)
