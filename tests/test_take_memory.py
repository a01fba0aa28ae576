"""Memory bounded by input: a take's declared size is checked from its .npy headers before any data is read,
and `convert` and `fit` read a chunk at a time (docs/cli.md#memory). Every command runs as a child process,
flockcal's command line as the installed `flockcal` runs it, and reports its own peak resident memory
(tests/peak_memory.py). The bound is the documented one, 3 × the input file + 150 MB."""

from __future__ import annotations

import gc
import struct
import tempfile
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest
from numpy.lib import format as npy

from flockcal import npz
from flockcal.drivers.recording import read_recording
from flockcal.simulator.fast_recording import write_recording
from flockcal.simulator.smooth_source import SmoothSource
from flockcal.take_files import TakeFile
from flockcal.takes import TakeError, load_take, make_take, save_take
from peak_memory import run_flockcal

MB = 1e6


def bound(path: Path) -> float:
    """The documented peak: 3 × the input file + 150 MB."""
    return 3 * path.stat().st_size + 150 * MB


def flockcal(*argv, env=None) -> tuple[int, str, float]:
    """(exit status, stderr, peak resident bytes) of `flockcal ARGV` in a child process."""
    rc, err, peak, _ = run_flockcal(*argv, env=env, timeout=600)
    return rc, err, peak


def zip_bomb(path: Path, frames: int, sensors: int) -> None:
    """A take .npz whose headers declare `frames` × `sensors` but whose members hold a few kB of zeros each
    (deflated to almost nothing): the file is tiny, its arrays would not fit in any machine."""
    declared = {"rotations": ((frames, sensors, 3, 3), "<f8"), "positions": ((frames, sensors, 3), "<f8"),
                "valid": ((frames, sensors), "|b1"), "times": ((frames,), "<f8")}
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, (shape, descr) in declared.items():
            with zf.open(name + ".npy", "w") as out:
                npy.write_array_header_1_0(out, {"descr": descr, "fortran_order": False, "shape": shape})
                out.write(bytes(65536))
        for name, array in (("names", np.array([f"s{i}" for i in range(sensors)])), ("rate_hz", np.float64(100))):
            with zf.open(name + ".npy", "w") as out:
                npy.write_array(out, array)


def test_a_zip_bomb_take_is_refused_from_its_headers_in_one_line(tmp_path):
    # Tried: the take, 10,000,000 frames of 16 sensors (15.6 GB of arrays) declared in a file of a few
    # kB, given to `fit` (which reads takes a chunk at a time) and to `export-bvh` (which loads one whole).
    # `fit` used to end in a 26-line ArrayMemoryError traceback.
    bomb = tmp_path / "bomb.npz"
    zip_bomb(bomb, 10_000_000, 16)
    assert bomb.stat().st_size < 50_000
    for argv in (["fit", bomb, "--json"], ["export-bvh", bomb, "-o", tmp_path / "out.bvh"]):
        rc, err, peak = flockcal(*argv)
        assert rc == 2 and err.count("\n") == 1, err
        assert f"{bomb}: its arrays unpack to 15.6 GB (10,000,000 frames of 16 sensors) from " in err, err
        assert "more than the 4 GB a take may unpack to" in err and "FLOCKCAL_MAX_TAKE_GB" in err, err
        assert peak <= bound(bomb), peak
    assert not (tmp_path / "out.bvh").exists()


def test_the_take_size_limit_is_an_option_and_a_variable(tmp_path):
    # Tried: a real take of 80,000 frames of 4 sensors (31.4 MB of arrays, all zeros but the times, so
    # the file is small) against a limit of 20 MB, by --max-take-gb and by FLOCKCAL_MAX_TAKE_GB; then
    # a limit it is within (the take is then read: all zeros, no joint turned, so fit's "too still" exit 3).
    n, m = 80_000, 4
    take = tmp_path / "zeros.npz"
    np.savez_compressed(take, rotations=np.zeros((n, m, 3, 3)), positions=np.zeros((n, m, 3)),
                        names=np.array(["a", "b", "c", "d"]), rate_hz=np.float64(100), times=np.arange(n) / 100)
    for argv, env in (([take, "--max-take-gb", "0.02"], None), ([take], {"FLOCKCAL_MAX_TAKE_GB": "0.02"})):
        rc, err, _ = flockcal("fit", *argv, env=env)
        assert rc == 2 and err.count("\n") == 1, err
        assert "its arrays unpack to 31.4 MB (80,000 frames of 4 sensors)" in err and "the 20 MB a take" in err
    rc, err, _ = flockcal("fit", take, "--max-take-gb", "0.04")
    assert rc == 3 and "too still to fit" in err, err
    rc, err, _ = flockcal("fit", take, env={"FLOCKCAL_MAX_TAKE_GB": "lots"})
    assert rc == 2 and "FLOCKCAL_MAX_TAKE_GB must be a positive number of gigabytes, got lots" in err, err


def test_a_take_loaded_whole_must_fit_in_the_memory_available(tmp_path, monkeypatch):
    # Tried: load_take (what the export commands use) on a 10,000-frame take when the machine has, as far
    # as the check can see, 1 MB available (MemAvailable read as 1 MB).
    src = SmoothSource(4)
    t = np.arange(10_000) / 100
    R, p, _ = src.poses(t)
    save_take(tmp_path / "t.npz", make_take(R, p, src.names, 100.0, times=t))
    monkeypatch.setattr(npz, "available_memory", lambda: 1_000_000)
    with pytest.raises(TakeError, match=r"its arrays unpack to 3.96 MB \(10,000 frames of 4 sensors\) from .*; "
                                        r"reading it whole needs up to 7.92 MB of memory and the machine has 1 MB"):
        load_take(tmp_path / "t.npz")


def test_convert_memory_does_not_grow_with_the_recording(tmp_path):
    # Tried: `convert` of a 1-minute and a 6-minute recording of 4 sensors at 100 Hz (0.4 and 2.6 MB).
    # Each peak is held to the documented bound; the longer one's to the shorter one's plus the growth of
    # the file itself, with 8 MB for the allocator's noise. Before chunked decoding, convert's peak grew 21
    # times as much as the file here (44 → 88 MB for these two; benchmarks/bench_memory.py: 706 MB for 45 MB).
    peaks, sizes = [], []
    for minutes in (1, 6):
        raw = tmp_path / f"{minutes}.fobraw"
        write_recording(raw, SmoothSource(4), 60 * minutes, 100.0)
        rc, err, peak = flockcal("convert", raw, "-o", tmp_path / f"{minutes}.npz")
        assert rc == 0, err
        assert f"wrote {tmp_path / f'{minutes}.npz'}: {6000 * minutes} frames of 4 sensors" in err, err
        assert peak <= bound(raw), (peak, raw.stat().st_size)
        peaks.append(peak)
        sizes.append(raw.stat().st_size)
    assert peaks[1] - peaks[0] <= (sizes[1] - sizes[0]) + 8 * MB, (peaks, sizes)
    with np.load(tmp_path / "6.npz") as take:  # and what it wrote is the whole recording
        assert take["rotations"].shape == (36_000, 4, 3, 3) and take["valid"].all()


def test_fit_of_a_take_stays_within_the_bound_with_its_exports(tmp_path):
    # Tried: `fit` of a 2-minute take of 6 sensors at 60 Hz with the slip search, a BVH and a glTF file,
    # the parts that used to hold the take whole (or several copies of it).
    take = tmp_path / "t.npz"
    rc, err, _ = flockcal("simulate", "--birds", 6, "--seconds", 120, "--rate", 60, "--motion", "exercise", "-o", take)
    assert rc == 0, err
    rc, err, peak = flockcal("fit", take, "--json", "--bvh", tmp_path / "t.bvh", "--gltf", tmp_path / "t.glb")
    assert rc == 0, err
    assert peak <= bound(take), (peak, take.stat().st_size)


def _chunk(kind: bytes, port: int, t: float, payload: bytes) -> bytes:
    """One .fobraw chunk with a valid checksum (drivers/recording.py's layout, written here independently)."""
    head = struct.pack("<2sccdI", b"CK", kind, bytes([port]), t, len(payload))
    return head + payload + struct.pack("<I", zlib.crc32(payload, zlib.crc32(head)))


def test_junk_chunks_with_valid_checksums_are_counted_located_and_skipped(tmp_path):
    # Tried: a 30 s recording followed by 2 MB of chunks with valid checksums holding random bytes, once with
    # random ports and times (raw random chunks), once on port 0 at times continuing the recording's (so only
    # their bytes give them away); and a recording header followed by random chunks alone. Convert used to
    # exit 0 without a word about them.
    clean = tmp_path / "clean.fobraw"
    write_recording(clean, SmoothSource(4), 30, 100.0)
    last = read_recording(clean).chunks[-1].time
    rng = np.random.default_rng(7)
    for case in ("random", "plausible"):
        raw = tmp_path / f"{case}.fobraw"
        data, junk, t = bytearray(clean.read_bytes()), 0, last
        start = len(data)
        while len(data) - start < 2_000_000:
            t += 0.02
            when = struct.unpack("<d", rng.bytes(8))[0] if case == "random" else t
            data += _chunk(b"R", int(rng.integers(0, 256)) if case == "random" else 0, when,
                           rng.bytes(int(rng.integers(64, 4096))))
            junk += 1
        raw.write_bytes(data)
        rc, err, _ = flockcal("convert", raw, "-o", tmp_path / f"{case}.npz")
        lines = err.strip().splitlines()
        assert rc == 3 and len(lines) == 2, err
        assert lines[0].startswith(f"wrote {tmp_path / f'{case}.npz'}: 3000 frames of 4 sensors"), err
        assert f"{raw}: {junk:,} junk chunks ({len(data) - start - 20 * junk:,} bytes) between bytes {start:,} and " \
               f"{len(data):,}" in lines[1], err
        with np.load(tmp_path / f"{case}.npz") as take:
            assert take["valid"].shape == (3000, 4)  # the recording's frames, and none made of junk

    header = clean.read_bytes()[:12 + struct.unpack_from("<I", clean.read_bytes(), 8)[0] + 4]
    alone = tmp_path / "alone.fobraw"
    alone.write_bytes(header + b"".join(_chunk(b"R", int(rng.integers(0, 256)), struct.unpack("<d", rng.bytes(8))[0],
                                               rng.bytes(1000)) for _ in range(200)))
    rc, err, _ = flockcal("convert", alone, "-o", tmp_path / "alone.npz")
    assert rc == 2 and err.count("\n") == 1, err
    assert "never reached streaming" in err and "200 junk chunks (200,000 bytes)" in err, err
    assert not (tmp_path / "alone.npz").exists()


def test_a_take_file_read_again_gives_the_same_frames_and_leaves_no_spool(tmp_path, monkeypatch):
    # Tried: a take file read in chunks of 1,000 frames, first a pass stopped after one chunk (as a rest-pose
    # search stops), then two whole passes (the second from the spooled arrays), each frame compared with
    # load_take's; then the TakeFile dropped. Its temporary folder must be gone after each of these.
    monkeypatch.setenv("TMPDIR", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    monkeypatch.setattr(tempfile, "tempdir", None)  # TMPDIR is read again
    src = SmoothSource(4)
    t = np.arange(5_500) / 100
    R, p, v = src.poses(t)
    v[::7, 2] = False
    save_take(tmp_path / "t.npz", make_take(R, p, src.names, 100.0, valid=v, times=t))
    whole = load_take(tmp_path / "t.npz")
    take = TakeFile(tmp_path / "t.npz")
    next(iter(take.chunks(1000)))
    assert list((tmp_path / "tmp").iterdir()) == []
    for _ in range(2):
        got = list(take.chunks(1000))
        assert [len(f) for f in got] == [1000] * 5 + [500]
        for name in ("times", "rotations", "positions", "valid"):
            assert np.array_equal(np.concatenate([getattr(f, name) for f in got]), getattr(whole, name)), name
    assert len(list((tmp_path / "tmp").iterdir())) == 1
    del take, got
    gc.collect()
    assert list((tmp_path / "tmp").iterdir()) == []
