"""Faults a vehicle meets: damaged or forged files are refused with their name, failing writes keep the old file."""
from __future__ import annotations

import errno
import os
import signal
import struct
import subprocess
import sys
import textwrap
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from lcpr_core.descriptor_map import DescriptorMap, MapConfig
from lcpr_core.errors import MapError

DIM = 16


def a_map(count: int, *, seed: int = 0) -> DescriptorMap:
    rng = np.random.default_rng(seed)
    m = DescriptorMap(MapConfig(dim=DIM))
    x = rng.normal(size=(count, DIM)).astype(np.float32)
    m.add(x / np.linalg.norm(x, axis=1, keepdims=True), stamps=np.arange(count, dtype=np.float64))
    return m


def test_a_bit_flipped_map_file_is_refused_naming_it_and_left_as_it_was(tmp_path: Path) -> None:
    path = tmp_path / "map.npz"
    a_map(200).save(path)
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo("descriptors.npy")
    data[info.header_offset + 30 + len(info.filename) + 200] ^= 0x10  # one bit inside the descriptors
    path.write_bytes(bytes(data))
    with pytest.raises(MapError, match="map.npz"):
        DescriptorMap.load(path)
    assert path.read_bytes() == bytes(data)


def _forge_shape(path: Path, member: str, shape: tuple[int, ...]) -> None:
    """Rewrite one member's .npy header to claim ``shape`` (same header length), keeping its data."""
    with zipfile.ZipFile(path) as zf:
        members = {i.filename: zf.read(i) for i in zf.infolist()}
    raw = members[member]
    header_len = struct.unpack("<H", raw[8:10])[0]
    header = raw[10:10 + header_len].decode("latin1")
    start = header.index("'shape': (")
    end = header.index(")", start) + 1
    forged = header[:start] + f"'shape': {shape!r}" + header[end:]
    forged = forged.rstrip().ljust(header_len - 1) + "\n"
    assert len(forged) == header_len, "the forged header must keep its length"
    members[member] = raw[:10] + forged.encode("latin1") + raw[10 + header_len:]
    with zipfile.ZipFile(path, "w") as zf:
        for name, content in members.items():
            zf.writestr(name, content)


def test_a_vseq2pc_scan_database_with_a_forged_array_is_refused_the_same_way(tmp_path: Path) -> None:
    from lcpr_core.vseq2pc.retrieval import ScanDatabase

    path = tmp_path / "scans.npz"
    db = ScanDatabase(weights_id="w")
    db.add(np.zeros((2, 8, 288), np.float32), stamps=[0.0, 1.0])
    db.save(path)
    _forge_shape(path, "descriptors.npy", (10**12, 8, 288))
    with pytest.raises(MapError, match=r"scan database .*scans\.npz.*claims shape \(1000000000000, 8, 288\)"):
        ScanDatabase.load(path)


def test_a_map_whose_arrays_claim_absurd_sizes_is_refused_before_allocating(tmp_path: Path) -> None:
    path = tmp_path / "forged.npz"
    a_map(10).save(path)
    _forge_shape(path, "descriptors.npy", (10**12, DIM))  # 64 TB of float32
    with pytest.raises(MapError, match=r"forged\.npz.*claims shape \(1000000000000, 16\)"):
        DescriptorMap.load(path)


def fill_the_disk(monkeypatch: pytest.MonkeyPatch) -> None:
    """From now on every map write fails as on a full disk (ENOSPC)."""
    def full(*args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(np, "savez", full)


def test_a_full_disk_during_save_keeps_the_old_map_and_raises_with_the_cause(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "map.npz"
    a_map(20).save(path)
    before = path.read_bytes()
    fill_the_disk(monkeypatch)
    with pytest.raises((MapError, OSError), match="No space left"):
        a_map(40, seed=1).save(path)
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["map.npz"]  # no temporary file left behind
    assert len(DescriptorMap.load(path)) == 20


def test_a_read_only_map_directory_refuses_the_save_and_keeps_the_old_map(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "map.npz"
    a_map(20).save(path)
    before = path.read_bytes()
    import tempfile

    def read_only(*args: object, **kwargs: object) -> None:  # what mkstemp meets in a read-only directory
        raise PermissionError(errno.EACCES, "Permission denied", str(tmp_path))
    monkeypatch.setattr(tempfile, "mkstemp", read_only)  # chmod alone does not stop root, who runs CI
    with pytest.raises((MapError, OSError), match="Permission denied"):
        a_map(40, seed=1).save(path)
    assert path.read_bytes() == before


@pytest.mark.slow
def test_a_save_killed_with_sigkill_leaves_the_old_map_intact_and_loadable(tmp_path: Path) -> None:
    """SIGKILL while a large map is being written: the file on disk is the old map, whole."""
    path = tmp_path / "map.npz"
    a_map(50).save(path)
    before = path.read_bytes()
    child = textwrap.dedent(f"""
        import numpy as np, sys
        from lcpr_core.descriptor_map import DescriptorMap, MapConfig
        m = DescriptorMap(MapConfig(dim=256))
        x = np.random.default_rng(0).normal(size=(400_000, 256)).astype(np.float32)
        m.add(x, stamps=np.arange(len(x), dtype=np.float64))
        print("saving", flush=True)
        while True:
            m.save({str(path)!r})
    """)
    proc = subprocess.Popen([sys.executable, "-c", child], stdout=subprocess.PIPE, text=True,
                            cwd=Path(__file__).resolve().parents[2])
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "saving"
        deadline = time.monotonic() + 60
        while not any(p.name.startswith(".map.npz.") for p in tmp_path.iterdir()):  # a write is under way
            assert time.monotonic() < deadline and proc.poll() is None
            time.sleep(0.005)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(30)
    loaded = DescriptorMap.load(path)  # whichever map it is, it is whole
    assert len(loaded) in (50, 400_000)
    if len(loaded) == 50:
        assert path.read_bytes() == before


def test_the_save_map_service_answers_a_full_disk_with_the_cause_and_the_old_map_stays(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """What ~/save_map does (ros_common.mapstore): success false, the OS error in the message, nothing raised."""
    from types import SimpleNamespace

    from lcpr_ros.mapstore import save_map
    from ros_common.mapstore import answer_save_request

    path = tmp_path / "map.npz"
    a_map(20).save(path)
    before = path.read_bytes()
    logged: list[str] = []
    fill_the_disk(monkeypatch)
    response = answer_save_request(SimpleNamespace(success=None, message=""), lambda: save_map(a_map(40), str(path)),
                                   what="places", path=str(path), log=logged.append)
    assert response.success is False and "No space left on device" in response.message and str(path) in response.message
    assert path.read_bytes() == before and logged == []


def test_a_truncated_weights_file_is_refused_with_its_path(tmp_path: Path) -> None:
    """The bundled checkpoint cut short, as an interrupted copy leaves it."""
    from lcpr_core.errors import CheckpointError
    from lcpr_core.lcpr.checkpoint import load_weights
    from lcpr_core.lcpr.describer import checkpoint_config
    from lcpr_core.lcpr.models import LCPR

    bundled = Path(__file__).resolve().parents[2] / "weights" / "lcpr_synth_narrow.pth"
    config = checkpoint_config(bundled)
    assert config is not None
    model = LCPR(width=config["width"])
    load_weights(model, bundled)  # whole, it loads
    cut = tmp_path / "cut.pth"
    cut.write_bytes(bundled.read_bytes()[: bundled.stat().st_size // 2])
    with pytest.raises(CheckpointError, match=r"cut\.pth' is not a readable PyTorch file"):
        load_weights(model, cut)
