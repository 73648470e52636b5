"""Shared fixtures: isolated DDS discovery, rclpy contexts, node subprocesses, sample messages,
one demo run.

The session fixture ``ros_domain`` reserves a ROS_DOMAIN_ID and limits discovery to this host
in os.environ before any test initialises rclpy; every subprocess inherits it, so parallel
test runs and anything else on the machine cannot cross-talk.

This folder is put on ``sys.path``, so that tests import shared plain modules (``jacobians``,
``strategies``, ``waiting``) under ``--import-mode=importlib``; property-based tests run
under one fixed hypothesis profile (derandomised, so every run draws the same examples).
"""

from __future__ import annotations

import array
import importlib
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import settings

from csam_ros.run.ros_env import isolate_this_process, reserve_domain_id

REPO = Path(__file__).resolve().parents[1]
CUSTOM_MSG_DIR = REPO / "msg_defs" / "msg"

if str(Path(__file__).parent) not in sys.path:
    sys.path.insert(0, str(Path(__file__).parent))

settings.register_profile(
    "csam", max_examples=60, deadline=None, derandomize=True, database=None, print_blob=True
)
settings.load_profile("csam")


@pytest.fixture(scope="session", autouse=True)
def ros_domain() -> Iterator[int]:
    """This session's ROS_DOMAIN_ID (also in os.environ, with LOCALHOST discovery)."""
    with reserve_domain_id() as reservation:
        isolate_this_process(reservation.domain_id)
        yield reservation.domain_id


@pytest.fixture
def ros_context(ros_domain: int) -> Iterator[Any]:
    """A fresh, initialised rclpy Context of its own, shut down after the test."""
    import rclpy
    from rclpy.context import Context

    context = Context()
    rclpy.init(context=context, domain_id=ros_domain)
    yield context
    rclpy.try_shutdown(context=context)


def spin_until(executor: Any, condition: Callable[[], bool], timeout_s: float = 10.0) -> bool:
    """Spin ``executor`` until ``condition()`` holds or ``timeout_s`` passes."""
    from waiting import wait_until  # this folder is on sys.path once conftest has run

    return wait_until(condition, timeout_s, lambda: executor.spin_once(timeout_sec=0.02))


@pytest.fixture
def spin() -> Callable[..., bool]:
    """spin(executor, condition, timeout_s=10): spin until the condition holds."""
    return spin_until


def executable(name: str) -> Path:
    """An entry point of this environment (``.venv/bin/<name>``)."""
    return Path(sys.prefix) / "bin" / name


class NodeProcesses:
    """Node executables started as subprocesses; each one ended by its pid at teardown."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.processes: list[subprocess.Popen[bytes]] = []

    def start(self, name: str, *args: str | Path) -> subprocess.Popen[bytes]:
        index = len(self.processes)
        stdout = (self.log_dir / f"{index}_{name}.out").open("wb")
        stderr = (self.log_dir / f"{index}_{name}.err").open("wb")
        process = subprocess.Popen(
            [str(executable(name)), *map(str, args)], stdout=stdout, stderr=stderr
        )
        process.stdout_path = Path(stdout.name)  # type: ignore[attr-defined]
        process.stderr_path = Path(stderr.name)  # type: ignore[attr-defined]
        stdout.close()
        stderr.close()
        self.processes.append(process)
        return process

    def stop(self, process: subprocess.Popen[bytes], sig: int = signal.SIGINT) -> int:
        """Send ``sig`` and wait for the exit code."""
        if process.poll() is None:
            process.send_signal(sig)
        return process.wait(timeout=20)

    @staticmethod
    def output(process: subprocess.Popen[bytes]) -> str:
        """stdout followed by stderr of a process started here (read after it ended)."""
        paths = (process.stdout_path, process.stderr_path)  # type: ignore[attr-defined]
        return "".join(Path(p).read_text(errors="replace") for p in paths)

    @staticmethod
    def stderr(process: subprocess.Popen[bytes]) -> str:
        return Path(process.stderr_path).read_text(errors="replace")  # type: ignore[attr-defined]

    def terminate_all(self) -> None:
        for process in self.processes:
            if process.poll() is None:
                process.kill()
                process.wait(timeout=10)


@pytest.fixture
def nodes(tmp_path: Path) -> Iterator[NodeProcesses]:
    """Start node executables; any still running at the end of the test is killed."""
    log_dir = tmp_path / "logs"
    log_dir.mkdir()
    processes = NodeProcesses(log_dir)
    yield processes
    processes.terminate_all()


# -- sample messages with every field set to a non-default value ------------------------------


def custom_msgtypes() -> list[str]:
    """Every message type defined in msg_defs/msg."""
    return [f"csam_msgs/msg/{path.stem}" for path in sorted(CUSTOM_MSG_DIR.glob("*.msg"))]


def message_class_of(msgtype: str) -> type:
    package, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), name)


class _Values:
    """Distinct non-default values: counter-based, exactly representable as float32."""

    def __init__(self) -> None:
        self.counter = 0

    def next(self) -> int:
        self.counter += 1
        return self.counter


def _value(slot: Any, values: _Values) -> Any:
    from rosidl_parser import definition as d

    if isinstance(slot, d.NamespacedType):
        return fill_message(message_class_of("/".join([*slot.namespaces, slot.name])), values)
    if isinstance(slot, d.AbstractNestedType):
        size = slot.size if isinstance(slot, d.Array) else 2
        if isinstance(slot, d.BoundedSequence):
            size = min(size, slot.maximum_size)
        return [_value(slot.value_type, values) for _ in range(size)]
    if isinstance(slot, d.AbstractGenericString):
        return f"s{values.next()}"
    if isinstance(slot, d.BasicType):
        n = values.next()
        if slot.typename == "boolean":
            return True
        if slot.typename in ("float", "double", "long double"):
            return n + 0.25 if n % 2 else -(n + 0.5)
        if slot.typename in ("octet", "char"):
            return bytes([n % 255 + 1]) if slot.typename == "octet" else chr(n % 94 + 33)
        if slot.typename.startswith("u") or slot.typename == "uint8":
            return n % 200 + 1
        return n % 100 + 1 if n % 2 else -(n % 100 + 1)
    raise TypeError(f"no sample value for slot type {slot!r}")


def fill_message(cls: type, values: _Values | None = None) -> Any:
    """An instance of ``cls`` with every field (recursively) set to a non-default value."""
    values = values or _Values()
    message = cls()
    for name, slot in zip(cls.get_fields_and_field_types(), cls.SLOT_TYPES, strict=True):
        setattr(message, name, _value(slot, values))
    return message


@pytest.fixture(scope="session")
def sample_messages() -> dict[str, Any]:
    """msgtype -> an rclpy message with non-default values, for every csam_msgs type."""
    return {msgtype: fill_message(message_class_of(msgtype)) for msgtype in custom_msgtypes()}


def _is_message(value: Any) -> bool:
    return hasattr(type(value), "get_fields_and_field_types")


def assert_fields_equal(expected: Any, actual: Any, path: str = "msg") -> None:
    """Compare an rclpy message field by field (recursively, exact) with ``actual``: an rclpy
    message, a rosbags message or an mcap_ros2 decoded message."""
    if _is_message(expected):
        for name in type(expected).get_fields_and_field_types():
            assert hasattr(actual, name), f"{path}: no field {name} in {type(actual).__name__}"
            assert_fields_equal(getattr(expected, name), getattr(actual, name), f"{path}.{name}")
    elif isinstance(expected, list | tuple | array.array | np.ndarray | bytes):
        actual_items = list(actual)
        assert len(actual_items) == len(expected), f"{path}: length {len(actual_items)}"
        for i, (e, a) in enumerate(zip(expected, actual_items, strict=True)):
            assert_fields_equal(e, a, f"{path}[{i}]")
    else:
        assert expected == actual, f"{path}: expected {expected!r}, got {actual!r}"


def assert_no_default_leaf(message: Any, path: str = "msg") -> None:
    """Every leaf of ``message`` differs from its type's default and no sequence is empty."""
    if _is_message(message):
        for name in type(message).get_fields_and_field_types():
            assert_no_default_leaf(getattr(message, name), f"{path}.{name}")
    elif isinstance(message, list | tuple | array.array | np.ndarray):
        assert len(message) > 0, f"{path} is empty"
        for i, item in enumerate(message):
            assert_no_default_leaf(item, f"{path}[{i}]")
    else:
        assert message not in (0, 0.0, "", False, b"\x00"), f"{path} = {message!r} is a default"


@pytest.fixture(scope="session")
def fields_equal() -> Callable[[Any, Any], None]:
    """assert_fields_equal(expected_rclpy_message, actual_message)."""
    return assert_fields_equal


@pytest.fixture(scope="session")
def no_default_leaf() -> Callable[[Any], None]:
    """assert_no_default_leaf(message): every leaf differs from its default."""
    return assert_no_default_leaf


@pytest.fixture(scope="session")
def make_sample() -> Callable[[str], Any]:
    """make_sample(msgtype): a fresh message of any type with every field non-default."""
    return lambda msgtype: fill_message(message_class_of(msgtype))


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One ``csam demo`` of the map-joining experiment for every test that reads a demo's run
    folder (summary, figures, bag): at rate 8, so its maps arrive spread over seconds."""
    out = tmp_path_factory.mktemp("demo") / "run"
    done = subprocess.run(
        [sys.executable, "-m", "csam_ros.cli", "demo", "--scenario", "map_joining"]
        + ["--rate", "8", "--isolated", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=240,
        cwd=REPO,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    return out
