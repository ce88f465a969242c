"""The native ``.amrb`` file (`mi_amr.data.amrb`): what is written reads back
exactly, the medium and the command line open it, and every kind of damage
is refused with one line naming the file and the problem."""

import os
import struct

import numpy as np
import pytest

import mi_amr
import mi_amr.data.amrb
from mi_amr.data.amrb import AmrbError, read_amrb, read_header, write_amrb
from mi_amr.data.blocks import BlockVolume
from mi_amr.data.datasets import make_dataset
from mi_amr.data.io import load_volume, save_cells

from conftest import HANG_S, random_amr


@pytest.fixture(scope="module")
def volume():
    v = BlockVolume.from_cells(make_dataset("blocks", cells=6000, seed=2))
    v.meta = {"field": "density", "units": "g/cm**3"}
    return v


@pytest.fixture
def written(volume, tmp_path):
    from mi_amr.native_file import save_native
    return save_native(volume, tmp_path / "v.amrb")              # with the stored grids


def assert_same(a: BlockVolume, b: BlockVolume):
    assert a.block == b.block and a.n_cells == b.n_cells and a.source == b.source and a.meta == b.meta
    for name in ("level", "coord", "origin", "lo", "hi"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    np.testing.assert_array_equal(a.values.view(np.uint32), b.values.view(np.uint32))   # NaNs too
    assert a.value_range == b.value_range
    assert (a.covers_bounds, a.partial_block_cells) == (b.covers_bounds, b.partial_block_cells)


def test01_round_trip_is_exact(volume, written, monkeypatch):
    back = read_amrb(written)
    assert_same(volume, back)
    assert back.values.dtype == np.float32 and back.coord.dtype == np.int32 and back.level.dtype == np.uint8
    assert_same(volume, load_volume(written))
    header = read_header(written)
    assert all(s["offset"] % 64 == 0 for s in header["sections"].values())
    # the stored grids are the ones a medium would build, for each method
    from mi_amr.structures.cost_model import file_grids
    expected = file_grids(volume)
    assert set(back.stored_grids) == set(expected) == {"nearest", "tent"}
    for method, g in expected.items():
        for field in ("res", "vmin", "vmax", "bits", "masks"):
            if g[field] is None:
                assert back.stored_grids[method][field] is None
            else:
                np.testing.assert_array_equal(back.stored_grids[method][field], g[field])
        assert back.stored_grids[method]["bins"] == g["bins"]
    assert expected["nearest"]["masks"] is not None and expected["tent"]["masks"] is None
    # an empty volume and one whose values span several checksummed chunks
    empty = BlockVolume.from_dense(np.full((4, 4, 4), np.nan, np.float32), block=4)
    assert len(read_amrb(write_amrb(empty, written.with_name("e.amrb"))).level) == 0
    monkeypatch.setattr(mi_amr.data.amrb, "CHUNK_BYTES", 1 << 12)          # many chunks, read in parallel
    big = BlockVolume.from_dense(np.random.default_rng(0).random((40, 40, 48), np.float32), block=8)
    path = write_amrb(big, written.with_name("b.amrb"))
    assert len(read_header(path)["sections"]["values"]["crc32"]) > 16
    monkeypatch.setattr(mi_amr.data.amrb, "CHUNK_BYTES", 1 << 20)          # the file's own chunk size is used
    assert_same(big, read_amrb(path))


def test02_the_medium_and_the_cli_open_it(llvm, volume, tmp_path, monkeypatch):
    """``filename="X.amrb"`` gives the medium the same data as the blocks
    themselves and the same majorants from the stored grids, without
    building one; ``mi-amr convert`` writes it from a .cells file and
    ``mi-amr render X.amrb`` renders it."""
    import mitsuba as mi
    from mi_amr.structures import macrocell_grid
    from mi_amr.tools.cli import main
    cells = random_amr(4, 16, 3)
    save_cells(cells, tmp_path / "c.cells")
    assert main(["convert", str(tmp_path / "c.cells"), str(tmp_path / "c.amrb")]) == 0
    assert_same(load_volume(tmp_path / "c.cells"), read_amrb(tmp_path / "c.amrb"))
    for method in ("tent", "nearest"):
        b = mi.load_dict({"type": "amr", "filename": str(tmp_path / "c.cells"), "transfer_function": "spiky",
                          "reconstruction": method})
        with monkeypatch.context() as m:                    # from the file, no grid is built
            m.setattr(macrocell_grid, "_RangeSplat", None)
            a = mi.load_dict({"type": "amr", "filename": str(tmp_path / "c.amrb"),
                              "transfer_function": "spiky", "reconstruction": method})
        np.testing.assert_array_equal(a.majorant_grid, b.majorant_grid)
        del a, b
    from conftest import render_cli
    r = render_cli([tmp_path / "c.amrb", "-o", tmp_path / "o.exr", "--spp", "1", "--res", "16"])
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "o.exr").is_file() and (tmp_path / "o.xml").is_file()
    assert not list(tmp_path.glob("*.tmp-*"))


def _refused(path, match):
    with pytest.raises(AmrbError, match=match) as e:
        read_amrb(path)
    message = str(e.value)
    assert str(path) in message and "\n" not in message
    return message


def test03_damage_is_refused_with_one_line(written):
    data = written.read_bytes()
    header = read_header(written)
    values = header["sections"]["values"]
    bad = written.with_name("bad.amrb")

    bad.write_bytes(data[:values["offset"] + values["nbytes"] // 2])          # truncated
    _refused(bad, "truncated")
    bad.write_bytes(data[:20])
    _refused(bad, "not an mi-amr|truncated")
    bad.write_bytes(data + b"x")
    _refused(bad, "trailing data")
    assert len(header["sections"]) == 3 + 7                                    # blocks and two grids
    for name in header["sections"]:                                            # one flipped bit per section
        s = header["sections"][name]
        at = s["offset"] + s["nbytes"] // 2
        bad.write_bytes(data[:at] + bytes([data[at] ^ 0x10]) + data[at + 1:])
        _refused(bad, f"section '{name}' is corrupted")
    at = 32 + 10                                                               # in the header's JSON
    bad.write_bytes(data[:at] + bytes([data[at] ^ 0x01]) + data[at + 1:])
    _refused(bad, "header is corrupted")
    bad.write_bytes(data[:8] + struct.pack("<I", 3) + data[12:])               # another version
    _refused(bad, "format version 3, this mi-amr reads versions 1, 2")
    import json
    import zlib
    n = struct.unpack_from("<I", data, 12)[0]
    head = json.loads(data[32:32 + n])
    head["sections"][2]["offset"] = 8                                          # a crafted header, checksum right
    text = json.dumps(head).encode()
    bad.write_bytes(data[:12] + struct.pack("<II", len(text), zlib.crc32(text)) + data[20:32] + text
                    + data[32 + n:])
    _refused(bad, "bad offset")
    bad.write_bytes(data[:12] + struct.pack("<I", 0xFFFFFFF0) + data[16:])    # a damaged header length
    _refused(bad, "damaged header length")
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + data[8:])                           # not ours
    _refused(bad, "not an mi-amr .amrb file")
    bad.write_bytes(data.replace(b"MIAMRB\r\n", b"MIAMRB\n\n", 1))             # a text-mode copy
    _refused(bad, "damaged signature")


def test04_the_cli_names_the_damage_in_one_line(written, tmp_path, capsys):
    from mi_amr.tools.cli import main
    data = bytearray(written.read_bytes())
    data[-3] ^= 0xFF
    bad = tmp_path / "bad.amrb"
    bad.write_bytes(bytes(data))
    capsys.readouterr()
    assert main(["render", str(bad), "-o", str(tmp_path / "o.exr"), "-q"]) == 2
    assert not (tmp_path / "o.exr").exists()
    err = capsys.readouterr().err
    lines = [l for l in err.splitlines() if l.strip()]
    assert len(lines) == 1 and str(bad) in lines[0] and "corrupted" in lines[0], err


def test05_an_interrupted_write_leaves_nothing_under_the_target(volume, tmp_path, monkeypatch):
    """A write that fails half-way (here: the disk fills after 1000 bytes)
    leaves neither the target nor its temporary file; an earlier file under
    the target name is left as it was."""
    target = tmp_path / "v.amrb"
    import builtins
    real_open = builtins.open

    class Full:
        def __init__(self, f):
            self.f, self.n = f, 0

        def write(self, b):
            self.n += len(b)
            if self.n > 1000:
                raise OSError(28, "No space left on device")
            return self.f.write(b)

        def __getattr__(self, name):
            return getattr(self.f, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return self.f.__exit__(*exc)

    def full_open(path, mode="r", *a, **k):
        f = real_open(path, mode, *a, **k)
        return Full(f) if "w" in mode and str(path).endswith(f".tmp-{os.getpid()}") else f

    monkeypatch.setattr(builtins, "open", full_open)
    with pytest.raises(OSError, match="No space"):
        write_amrb(volume, target)
    assert not target.exists() and not list(tmp_path.iterdir())
    monkeypatch.setattr(builtins, "open", real_open)
    write_amrb(volume, target)
    before = target.read_bytes()
    monkeypatch.setattr(builtins, "open", full_open)
    with pytest.raises(OSError):
        write_amrb(BlockVolume.from_cells(random_amr(5, 8, 2)), target)
    assert target.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["v.amrb"]
    # Ctrl-C half-way through the sections: the same
    monkeypatch.setattr(Full, "write", lambda self, b: (_ for _ in ()).throw(KeyboardInterrupt())
                        if self.f.tell() > 500 else self.f.write(b))
    with pytest.raises(KeyboardInterrupt):
        write_amrb(BlockVolume.from_cells(random_amr(6, 8, 2)), target)
    assert target.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["v.amrb"]


def test06_version_1_files_open_without_grids(volume, tmp_path):
    """A file without stored grids (as version 1 wrote them) opens; a
    header whose grid sections do not match is refused."""
    import json
    import zlib
    plain = write_amrb(volume, tmp_path / "p.amrb")
    data = plain.read_bytes()
    old = tmp_path / "v1.amrb"
    old.write_bytes(data[:8] + struct.pack("<I", 1) + data[12:])
    back = read_amrb(old)
    assert_same(volume, back) and back.stored_grids == {}
    n = struct.unpack_from("<I", data, 12)[0]
    head = json.loads(data[32:32 + n])
    head["grids"] = [{"method": "tent", "res": [4, 4, 4], "arrays": ["vmin", "vmax", "bits"], "bins": None}]
    text = json.dumps(head).encode()
    bad = tmp_path / "bad.amrb"
    bad.write_bytes(data[:12] + struct.pack("<II", len(text), zlib.crc32(text)) + data[20:32] + text
                    + data[32 + n:])
    _refused(bad, "header is malformed|not those the header describes")


def _interrupt_while_reading(argv, files, timeout=HANG_S):
    """Run ``python -m mi_amr.tools.cli *argv``, send it SIGINT once it has
    one of ``files`` open, and return ``(returncode, stderr, seconds from the
    signal to the exit)``."""
    import signal
    import subprocess
    import sys
    import time
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    # SIGINT as a terminal delivers it: a runner that starts the suite in the
    # background (``cmd &``) passes SIGINT on ignored, and Python then keeps ignoring it
    proc = subprocess.Popen([sys.executable, "-m", "mi_amr.tools.cli", *argv],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    files = {str(f) for f in files}
    try:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and proc.poll() is None:       # until it reads the cells
            try:
                open_now = {os.readlink(f"/proc/{proc.pid}/fd/{fd}") for fd in os.listdir(f"/proc/{proc.pid}/fd")}
            except OSError:                                              # an fd closed while listed
                continue
            if open_now & files:
                break
            time.sleep(0.002)
        assert proc.poll() is None, "the command ended before it could be interrupted"
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=timeout)
        return proc.returncode, err, time.monotonic() - t0
    finally:
        proc.kill()


@pytest.fixture(scope="module")
def big_cells(tmp_path_factory):
    """A .cells file of 3 x 10^6 cells: loading it takes seconds."""
    from mi_amr.data.datasets import write_block_dataset
    return write_block_dataset(tmp_path_factory.mktemp("big") / "big.cells", 3_000_000, 4)


def test07_ctrl_c_during_a_conversion_stops_it_cleanly(big_cells, tmp_path):
    """SIGINT while ``mi-amr convert`` is reading a .cells file: exit status
    130 and one line saying so, and nothing under the target name or a
    temporary one: it stopped, not finished (a real process, a real
    signal; no deadline but a hang's)."""
    out = tmp_path / "big.amrb"
    rc, err, _ = _interrupt_while_reading(["convert", str(big_cells), str(out)],
                                          [big_cells, big_cells.with_suffix(".scalars")])
    assert rc == 130, err
    lines = [l for l in err.splitlines() if l.strip()]
    assert lines == ["mi-amr convert: interrupted"], err
    assert not out.exists() and not list(tmp_path.glob("*.tmp-*"))


def test08_ctrl_c_during_a_scene_load_stops_it_cleanly(big_cells, tmp_path):
    """SIGINT while ``mi-amr render scene.xml`` loads its medium's .cells
    file (inside Mitsuba's plugin constructor, which turns the interrupt
    into a RuntimeError): exit status 130 and the same one line."""
    from pathlib import Path
    scene = (Path(__file__).parents[1] / "scenes" / "blocks.xml").read_text()
    assert "data/blocks.cells" in scene
    xml = tmp_path / "big.xml"
    xml.write_text(scene.replace("data/blocks.cells", str(big_cells)))
    out = tmp_path / "big.exr"
    rc, err, _ = _interrupt_while_reading(["render", str(xml), "-o", str(out), "--spp", "1", "-D", "res=16"],
                                          [big_cells, big_cells.with_suffix(".scalars")])
    assert rc == 130, err
    lines = [l for l in err.splitlines() if l.strip()]
    assert lines == ["mi-amr render: interrupted"], err
    assert not out.exists()
