"""IF file formats: lossless round trips, sidecar, ION XML, inversion handling, errors."""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ultratight.errors import FormatError, InputFileError
from ultratight.signals.recording import iffile
from ultratight.signals.recording.iffile import FORMATS, IfWriter, open_if, write_if

LEVELS2 = np.array([-3, -1, 1, 3], dtype=np.float32)


def _random_samples(fmt, n, rng):
    spec = FORMATS[fmt]
    c = spec.comps
    if spec.packed2:
        comps = rng.choice(LEVELS2, size=n * c)
    elif fmt.endswith("i8"):
        comps = rng.integers(-128, 128, size=n * c).astype(np.float32)
    elif fmt.endswith("i16"):
        comps = rng.integers(-32768, 32768, size=n * c).astype(np.float32)
    else:
        comps = rng.standard_normal(n * c).astype(np.float32) * 100
    comps = comps.astype(np.float32)
    return comps.view(np.complex64) if spec.is_complex else comps


@pytest.mark.parametrize("fmt", sorted(FORMATS))
@pytest.mark.parametrize("n", [0, 1, 3, 4, 5, 1001])
def test_roundtrip_lossless(tmp_path, fmt, n):
    rng = np.random.default_rng(n)
    x = _random_samples(fmt, n, rng)
    p = tmp_path / f"x.{fmt}"
    write_if(p, x, fmt, 4e6, 0.0 if FORMATS[fmt].is_complex else 1e6, start_week=2190, start_tow_s=1.5)
    with open_if(p) as src:
        assert src.n_samples == n
        assert src.fmt == fmt
        assert src.start_week == 2190 and src.start_tow_s == 1.5
        y = src.read(0, n)
        assert y.dtype == (np.complex64 if FORMATS[fmt].is_complex else np.float32)
        np.testing.assert_array_equal(y, x)
        # every partial window agrees too
        if n > 3:
            np.testing.assert_array_equal(src.read(2, n - 3), x[2:n - 1])
            got = np.concatenate([b for _, b in src.blocks(7, start=1)])
            np.testing.assert_array_equal(got, x[1:])


@settings(max_examples=30, deadline=None)
@given(fmt=st.sampled_from(sorted(FORMATS)), n=st.integers(0, 50), start=st.integers(0, 60),
       count=st.integers(0, 60), seed=st.integers(0, 2**31))
def test_roundtrip_windows_hypothesis(tmp_path_factory, fmt, n, start, count, seed):
    x = _random_samples(fmt, n, np.random.default_rng(seed))
    p = tmp_path_factory.mktemp("h") / "x.bin"
    write_if(p, x, fmt, 2e6, 0.0 if FORMATS[fmt].is_complex else 0.5e6)
    with open_if(p) as src:
        np.testing.assert_array_equal(src.read(start, count), x[start:start + count])


def test_packed_bit_layout(tmp_path):
    # documented layout: first sample in bits 7-6, codes 0:+1 1:+3 2:-1 3:-3
    p = tmp_path / "p.bin"
    write_if(p, np.array([1, 3, -1, -3, -3], np.float32), "i2packed", 4e6, 1e6)
    raw = p.read_bytes()
    assert raw == bytes([0b00011011, 0b11000000])
    q = tmp_path / "q.bin"
    write_if(q, np.array([3 - 1j, -3 + 1j], np.complex64), "ci2packed", 4e6)
    assert q.read_bytes() == bytes([0b01101100])


def test_int_formats_are_little_endian(tmp_path):
    p = tmp_path / "a.bin"
    write_if(p, np.array([1 + 2j], np.complex64), "ci16", 1e6)
    assert p.read_bytes() == b"\x01\x00\x02\x00"


def test_sidecar_contents_and_flags_override(tmp_path):
    p = tmp_path / "s.bin"
    write_if(p, np.zeros(8, np.complex64), "ci8", 4e6, extra={"generator": {"seed": 3}})
    side = json.loads((tmp_path / "s.bin.json").read_text())
    for k in ("fs_hz", "if_hz", "format", "is_complex", "iq_conj", "start_week", "start_tow_s", "version"):
        assert k in side
    assert side["generator"] == {"seed": 3}
    with open_if(p, fs_hz=2e6) as src:
        assert src.fs_hz == 2e6 and src.duration_s == 8 / 2e6


def test_iq_conj_argument_and_sidecar(tmp_path):
    x = np.array([1 + 2j, -3 - 4j, 5 - 6j], np.complex64)
    p = tmp_path / "c.bin"
    write_if(p, x, "ci8", 4e6)
    with open_if(p, iq_conj=True) as src:
        np.testing.assert_array_equal(src.read(0, 3), np.conj(x))
    q = tmp_path / "d.bin"
    write_if(q, x, "ci8", 4e6, iq_conj=True)
    with open_if(q) as src:
        np.testing.assert_array_equal(src.read(0, 3), np.conj(x))
    with open_if(q, meta=str(q) + ".json") as src:
        np.testing.assert_array_equal(src.read(1, 2), np.conj(x[1:]))


def test_real_inversion_becomes_noninverted_tone(tmp_path):
    """A real inverted file at IF f holding cos(2 pi f t - phi(t)) is presented as a
    non-inverted signal at fs/2 - f: cos(2 pi (fs/2 - f) t + phi(t))."""
    fs, f_if, dop = 8e6, 1.5e6, 1234.0
    n = np.arange(4000)
    t = n / fs
    phi = 2 * np.pi * dop * t + 0.3
    x = 100 * np.cos(2 * np.pi * f_if * t - phi)
    p = tmp_path / "inv.bin"
    write_if(p, x.astype(np.float32), "f32", fs, f_if, inversion=True)
    with open_if(p) as src:
        assert src.if_hz == fs / 2 - f_if
        for start in (0, 1, 7):
            y = src.read(start, 1000)
            tt = (start + np.arange(1000)) / fs
            want = 100 * np.cos(2 * np.pi * src.if_hz * tt + 2 * np.pi * dop * tt + 0.3)
            np.testing.assert_allclose(y, want, atol=2e-3)


ION_XML = """<?xml version="1.0" encoding="UTF-8"?>
<metadata xmlns="http://www.ion.org/standards/sdrwg/schema/metadata.xsd">
  <lane id="L">
    <system id="S"/>
    <block>
      <cycles>1</cycles>
      <chunk>
        <sizeword>2</sizeword>
        <countwords>1</countwords>
        <endian>{endian}</endian>
        <lump>
          <stream id="L1">
            <ratefactor>2</ratefactor>
            <quantization>{quant}</quantization>
            <packedbits>{packed}</packedbits>
            <format>{fmt}</format>
            <encoding>{enc}</encoding>
            <band id="L1band">
              <centerfreq format="MHz">1575.42</centerfreq>
              <translatedfreq format="kHz">{if_khz}</translatedfreq>
            </band>
          </stream>
        </lump>
      </chunk>
    </block>
  </lane>
  <system id="S"><freqbase format="MHz">2.0</freqbase></system>
  <file><url>{url}</url><lane id="L"/></file>
</metadata>
"""


@pytest.mark.parametrize("quant,packed,fmt,enc,endian,ourfmt,dtype", [
    (8, 16, "IQ", "TC", "Little", "ci8", "i1"),
    (16, 32, "IQ", "INT16", "Big", "ci16", ">i2"),
    (8, 8, "IF", "TC", "Little", "i8", "i1"),
    (32, 64, "IQ", "FP", "Little", "cf32", "<f4"),
    (2, 2, "IF", "SM", "Little", "i2packed", None),
])
def test_ion_metadata_xml(tmp_path, quant, packed, fmt, enc, endian, ourfmt, dtype):
    rng = np.random.default_rng(1)
    is_c = FORMATS[ourfmt].is_complex
    x = _random_samples(ourfmt, 20, rng)
    if dtype is not None:
        comps = (x.view(np.float32) if is_c else x).astype(dtype)
        (tmp_path / "d.bin").write_bytes(comps.tobytes())
    else:
        write_if(tmp_path / "tmp.bin", x, ourfmt, 1.0)
        (tmp_path / "d.bin").write_bytes((tmp_path / "tmp.bin").read_bytes())
    xml = tmp_path / "d.xml"
    xml.write_text(ION_XML.format(quant=quant, packed=packed, fmt=fmt, enc=enc, endian=endian,
                                  if_khz=0 if is_c else 1000, url="d.bin"))
    with open_if(meta=xml) as src:
        assert src.fmt == ourfmt
        assert src.fs_hz == 4e6
        assert src.if_hz == (0.0 if is_c else 1e6)
        np.testing.assert_array_equal(src.read(0, 20), x)


def test_ion_metadata_inverted_and_qi(tmp_path):
    x = np.array([1 + 2j, 3 - 4j], np.complex64)
    (tmp_path / "d.bin").write_bytes(x.view(np.float32)[[1, 0, 3, 2]].astype(np.int8).tobytes())
    xml = tmp_path / "m.xml"
    xml.write_text(ION_XML.format(quant=8, packed=16, fmt="QIn", enc="TC", endian="Little", if_khz=0,
                                  url="d.bin"))
    with open_if(meta=xml) as src:
        np.testing.assert_array_equal(src.read(0, 2), np.conj(x))


# ---------------------------------------------------------------- errors
def test_size_not_whole_samples(tmp_path):
    p = tmp_path / "bad.bin"
    p.write_bytes(b"\x00" * 7)
    with pytest.raises(FormatError, match="not a whole number of ci16 samples"):
        open_if(p, fmt="ci16", fs_hz=4e6)


def test_unknown_format(tmp_path):
    p = tmp_path / "a.bin"
    p.write_bytes(b"\x00" * 8)
    with pytest.raises(FormatError, match="unknown IF sample format 'cs8'"):
        open_if(p, fmt="cs8", fs_hz=4e6)
    with pytest.raises(FormatError, match="unknown IF sample format"):
        IfWriter(tmp_path / "b.bin", "x", 1e6)


def test_no_sidecar_no_flags(tmp_path):
    p = tmp_path / "a.bin"
    p.write_bytes(b"\x00" * 8)
    with pytest.raises(FormatError, match="no sidecar"):
        open_if(p)
    with pytest.raises(FormatError, match="no sidecar"):
        open_if(p, fmt="ci8")


def test_missing_file(tmp_path):
    with pytest.raises(InputFileError, match="not found"):
        open_if(tmp_path / "nope.bin", fmt="ci8", fs_hz=4e6)


def test_messages_are_one_line(tmp_path):
    p = tmp_path / "bad.bin"
    p.write_bytes(b"\x00" * 3)
    with pytest.raises(FormatError) as ei:
        open_if(p, fmt="cf32", fs_hz=1e6)
    assert "\n" not in str(ei.value)


def test_writer_abort_leaves_nothing(tmp_path):
    p = tmp_path / "out.bin"
    with pytest.raises(RuntimeError):
        with IfWriter(p, "ci8", 4e6) as w:
            w.write(np.ones(10, np.complex64))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_reader_is_streaming_memmap(tmp_path):
    p = tmp_path / "big.bin"
    write_if(p, np.zeros(1000, np.complex64), "ci8", 1e6)
    with open_if(p) as src:
        assert isinstance(src._mm, np.memmap)


def test_format_table_documented():
    for name in FORMATS:
        assert f"``{name}``" in iffile.__doc__


def _mapping_rss_kb(path):
    """Resident kB of this process's mappings of ``path`` (Linux /proc/self/smaps), or None."""
    try:
        lines = open("/proc/self/smaps").read().splitlines()
    except OSError:
        return None
    total, inside = 0, False
    for ln in lines:
        parts = ln.split()
        if parts and "-" in parts[0] and len(parts) >= 5 and not parts[0].endswith(":"):
            inside = len(parts) >= 6 and parts[-1] == str(path)
        elif inside and parts[0] == "Rss:":
            total += int(parts[1])
    return total


@pytest.mark.parametrize("fmt", ["ci8", "i2packed"])
def test_release_drops_read_pages_and_reads_stay_correct(tmp_path, fmt):
    rng = np.random.default_rng(5)
    n = 1 << 20
    if fmt == "ci8":
        x = (rng.integers(-100, 100, n) + 1j * rng.integers(-100, 100, n)).astype(np.complex64)
    else:
        x = rng.choice(np.array([-3.0, -1.0, 1.0, 3.0], np.float32), n)
    p = tmp_path / f"rel_{fmt}.bin"
    write_if(p, x, fmt, 4e6)
    with open_if(p) as src:
        assert src.release(0) == 0
        for s, blk in src.blocks(1 << 16):
            pass
        before = _mapping_rss_kb(p.resolve())
        released = src.release(src.n_samples)
        nbytes = p.stat().st_size
        assert nbytes - 4096 < released <= nbytes
        after = _mapping_rss_kb(p.resolve())
        if before is not None and before > 0:
            assert after < 0.1 * before
        # released samples read back unchanged
        np.testing.assert_array_equal(src.read(1000, 5000), x[1000:6000])
        half = src.n_samples // 2
        got = src.release(half)
        assert got <= released and got % 4096 == 0
        np.testing.assert_array_equal(src.read(half - 3, 10), x[half - 3:half + 7])
    # closed source: nothing to release
    assert src.release(100) == 0


@pytest.mark.parametrize("fmt", sorted(FORMATS))
def test_format_object_encode_decode_without_files(fmt):
    """Each format is one object: its encoder's bytes decode back through the same object, and its
    byte counts agree with the encoded length."""
    spec = FORMATS[fmt]
    x = _random_samples(fmt, 37, np.random.default_rng(5))
    comps = np.ascontiguousarray(x).view(np.float32).reshape(-1)
    enc = spec.encoder()
    raw = enc.encode(comps) + enc.flush()
    lay = spec.layout()
    store = np.frombuffer(raw, dtype=np.dtype(spec.dtype))
    assert spec.count(len(raw), lay) >= 37 and spec.nbytes(36, lay) <= len(raw)
    np.testing.assert_array_equal(spec.decode(store, 3, 30, lay), comps[3 * spec.comps:33 * spec.comps])
    assert spec.quantiser_bits in (0, 2, 8, 16)
