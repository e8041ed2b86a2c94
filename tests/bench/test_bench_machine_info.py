# SPDX-License-Identifier: Apache-2.0
"""``machine_info`` and ``cpu_model`` of pugsd/bench/measure.py, pinned field by field from
stand-in sources: the report names the machine the figures came from."""

from __future__ import annotations

import io
import types
from collections.abc import Sequence
from typing import Any

import pytest

import pugsd.bench.measure as measure


def _fake_open(text: str | None) -> Any:
    def fake(path: str, *a: Any, **kw: Any) -> io.StringIO:
        assert path == "/proc/cpuinfo"
        if text is None:
            raise PermissionError(13, "Permission denied", path)
        return io.StringIO(text)

    return fake


def _platform(processor: str = "") -> types.SimpleNamespace:
    return types.SimpleNamespace(
        processor=lambda: processor,
        python_version=lambda: "3.12.9",
        platform=lambda: "Linux-6.1-x86_64-with-glibc2.36",
    )


def test_cpu_model_is_the_first_model_name_line(monkeypatch: pytest.MonkeyPatch) -> None:
    text = (
        "processor\t: 0\nvendor_id\t: GenuineIntel\n"
        "Model Name\t:  Intel(R) Xeon(R) CPU @ 2.20GHz: rev 7 \n"  # any case; ':' in the value kept
        "model name\t: the second core\n"
    )
    monkeypatch.setattr(measure, "open", _fake_open(text), raising=False)
    monkeypatch.setattr(measure, "platform", _platform("x86_64"))
    assert measure.cpu_model() == "Intel(R) Xeon(R) CPU @ 2.20GHz: rev 7"


@pytest.mark.parametrize("text", ["processor\t: 0\nHardware\t: BCM2835\n", None])
def test_cpu_model_falls_back_to_the_processor_then_unknown(
    monkeypatch: pytest.MonkeyPatch, text: str | None
) -> None:
    """No "model name" line (ARM) or no readable /proc/cpuinfo: platform.processor(), and
    "unknown" when that is empty too."""
    monkeypatch.setattr(measure, "open", _fake_open(text), raising=False)
    monkeypatch.setattr(measure, "platform", _platform("aarch64"))
    assert measure.cpu_model() == "aarch64"
    monkeypatch.setattr(measure, "platform", _platform(""))
    assert measure.cpu_model() == "unknown"


def _fake_torch(cuda: bool) -> types.SimpleNamespace:
    names: list[int] = []

    def device_name(i: int) -> str:
        names.append(i)
        return "H100"

    t = types.SimpleNamespace(
        __version__="2.9.1+cpu",
        get_num_threads=lambda: 3,
        cuda=types.SimpleNamespace(is_available=lambda: cuda, get_device_name=device_name),
        backends=types.SimpleNamespace(cpu=types.SimpleNamespace(get_cpu_capability=lambda: "AVX512")),
    )
    t.device_names = names
    return t


def _fake_os(affinity: bool) -> types.SimpleNamespace:
    o = types.SimpleNamespace(
        cpu_count=lambda: 16,
        environ={"OMP_NUM_THREADS": "2"},
        getloadavg=lambda: (0.123, 1.456, 2.0),
    )
    if affinity:
        o.sched_getaffinity = lambda pid: {0, 1, 5} if pid == 0 else set()
    return o


@pytest.fixture
def stand_ins(monkeypatch: pytest.MonkeyPatch) -> list[Sequence[str]]:
    asked: list[Sequence[str]] = []

    def versions(names: Sequence[str]) -> dict[str, str | None]:
        asked.append(tuple(names))
        return {n: "1.0" for n in names}

    monkeypatch.setattr(measure, "cpu_model", lambda: "Test CPU")
    monkeypatch.setattr(measure, "platform", _platform())
    monkeypatch.setattr(measure, "_package_versions", versions)
    memory = types.SimpleNamespace(total=int(15.66 * 2**30))
    monkeypatch.setattr(measure, "psutil", types.SimpleNamespace(virtual_memory=lambda: memory))
    return asked


def test_machine_info_reports_each_field_from_its_source(
    monkeypatch: pytest.MonkeyPatch, stand_ins: list[Sequence[str]]
) -> None:
    torch = _fake_torch(cuda=False)
    monkeypatch.setattr(measure, "torch", torch)
    monkeypatch.setattr(measure, "os", _fake_os(affinity=True))
    info = measure.machine_info("cpu")
    pkgs = ("numpy", "scipy", "gpytorch", "linear_operator", "opencv-python-headless", "open3d")
    assert info == {
        "cpu_model": "Test CPU",
        "logical_cores": 16,
        "affinity_cores": 3,
        "memory_gb": 15.7,
        "torch": "2.9.1+cpu",
        "torch_threads": 3,
        "omp_num_threads_env": "2",
        "device": "cpu",
        "cuda_available": False,
        "python": "3.12.9",
        "platform": "Linux-6.1-x86_64-with-glibc2.36",
        "load_average_at_start": [0.12, 1.46, 2.0],
        "torch_cpu_capability": "AVX512",
        "packages": {n: "1.0" for n in pkgs},
    }
    assert stand_ins == [pkgs] and torch.device_names == []  # no CUDA: no device name asked


def test_machine_info_names_the_cuda_device_and_no_affinity_off_linux(
    monkeypatch: pytest.MonkeyPatch, stand_ins: list[Sequence[str]]
) -> None:
    torch = _fake_torch(cuda=True)
    monkeypatch.setattr(measure, "torch", torch)
    fake_os = _fake_os(affinity=False)  # macOS: no sched_getaffinity
    fake_os.environ = {}
    monkeypatch.setattr(measure, "os", fake_os)
    info = measure.machine_info("cuda")
    assert info["affinity_cores"] is None and info["omp_num_threads_env"] is None
    assert info["device"] == "cuda" and info["cuda_available"] is True
    assert info["cuda_device"] == "H100" and torch.device_names == [0]


def test_package_versions_says_none_for_a_missing_package() -> None:
    got = measure._package_versions(("numpy", "pugsd-no-such-package-x"))
    assert got == {"numpy": measure.np.__version__, "pugsd-no-such-package-x": None}
