"""Start node executables as separate processes, like a launch file, and stop them all.

There is no ``ros2 launch`` here (docs/ENVIRONMENT.md); `csam demo` and `csam replay` use this small
process group instead. Each process logs to ``<log_dir>/<name>.log``; stopping sends SIGINT
(rclpy shuts down cleanly), then SIGTERM, then SIGKILL, and leaves no process behind.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path


def executable(name: str) -> str:
    """Path of a csam_ros executable next to this interpreter (the project's .venv/bin)."""
    candidate = Path(sys.executable).parent / name
    return str(candidate) if candidate.exists() else name


@dataclass
class ProcessGroup:
    """Child processes sharing one environment and one log directory."""

    log_dir: Path
    env: dict[str, str]
    processes: dict[str, subprocess.Popen] = field(default_factory=dict)

    def start(
        self, name: str, argv: list[str], env: dict[str, str] | None = None
    ) -> subprocess.Popen:
        """Start ``argv`` as ``name`` (its own session, its log file), in the group's
        environment or ``env``."""
        self.log_dir.mkdir(parents=True, exist_ok=True)
        log = open(self.log_dir / f"{name}.log", "wb")  # noqa: SIM115 (owned by the child)
        proc = subprocess.Popen(
            argv,
            env=self.env if env is None else env,
            stdout=log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )
        log.close()
        self.processes[name] = proc
        return proc

    def dead(self) -> dict[str, int]:
        """Processes that have exited, with their exit codes."""
        return {n: p.returncode for n, p in self.processes.items() if p.poll() is not None}

    def log_tail(self, name: str, lines: int = 15) -> str:
        path = self.log_dir / f"{name}.log"
        if not path.exists():
            return ""
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])

    def stop(self, name: str, timeout: float = 10.0) -> int | None:
        """Stop one process: SIGINT, then SIGTERM, then SIGKILL; its exit code."""
        proc = self.processes[name]
        for sig, wait in ((signal.SIGINT, timeout), (signal.SIGTERM, 3.0), (signal.SIGKILL, 3.0)):
            if proc.poll() is not None:
                break
            try:
                os.killpg(proc.pid, sig)
            except ProcessLookupError:
                break
            try:
                proc.wait(wait)
            except subprocess.TimeoutExpired:
                continue
        return proc.poll()

    def stop_all(self, timeout: float = 10.0) -> None:
        """Stop every process (in reverse start order)."""
        for name in reversed(list(self.processes)):
            self.stop(name, timeout)

    def wait(self, name: str, timeout: float) -> int | None:
        try:
            return self.processes[name].wait(timeout)
        except subprocess.TimeoutExpired:
            return None

    def __enter__(self) -> ProcessGroup:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop_all()


def wait_until(predicate, timeout: float, period: float = 0.05) -> bool:
    """Poll ``predicate`` until it holds or ``timeout`` seconds pass."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period)
    return bool(predicate())
