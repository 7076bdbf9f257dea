"""Packed 2-bit and 4-bit samples in every layout (bit order, word size, byte order, encoding)."""

import itertools
import json
import subprocess
import sys

import numpy as np
import pytest

from ultratight.errors import ConfigError
from ultratight.signals.recording.iffile import open_if
from ultratight.signals.recording.packing import ENCODINGS, PackedLayout


def test_levels_of_every_encoding():
    L = lambda **k: PackedLayout(**k).levels().tolist()           # noqa: E731
    assert L(bits=2, encoding="sign-magnitude") == [1, 3, -1, -3]    # the project's i2packed codes
    assert L(bits=2, encoding="twos-complement") == [1, 3, -3, -1]   # v = 0, 1, -2, -1 -> 2v + 1
    assert L(bits=2, encoding="offset-binary") == [-3, -1, 1, 3]     # v = c - 2
    assert L(bits=2, encoding="sign") == [1, 1, -1, -1]
    assert L(bits=4, encoding="sign-magnitude") == [1, 3, 5, 7, 9, 11, 13, 15, -1, -3, -5, -7, -9, -11, -13, -15]
    assert L(bits=4, encoding="twos-complement")[7:10] == [15, -15, -13]
    assert L(bits=4, encoding="offset-binary")[0] == -15 and L(bits=4, encoding="offset-binary")[8] == 1
    with pytest.raises(ConfigError, match="--packing"):
        PackedLayout(order="middle")
    with pytest.raises(ConfigError, match="--word-size"):
        PackedLayout(word_bytes=3)


def _pack_reference(codes, bits, order, word_bytes, endian):
    """Plain-Python packer (independent of PackedLayout.pack): samples into integer words."""
    per = 8 * word_bytes // bits
    out = bytearray()
    for w0 in range(0, len(codes), per):
        word = 0
        for k, c in enumerate(codes[w0:w0 + per]):
            shift = 8 * word_bytes - bits * (k + 1) if order == "msb-first" else bits * k
            word |= int(c) << shift
        out += word.to_bytes(word_bytes, endian)
    return bytes(out)


LAYOUTS = list(itertools.product((2, 4), ("msb-first", "lsb-first"), (1, 2, 4, 8), ("little", "big"), ENCODINGS))


@pytest.mark.parametrize("bits,order,wb,endian,enc", LAYOUTS)
def test_every_layout_reads_back(tmp_path, bits, order, wb, endian, enc):
    rng = np.random.default_rng(bits * 1000 + wb)
    cplx = wb == 2                        # complex and real both covered
    per = 8 * wb // bits
    n_comp = per * 37
    codes = rng.integers(0, 1 << bits, size=n_comp)
    p = tmp_path / "x.bin"
    p.write_bytes(_pack_reference(codes, bits, order, wb, endian))
    lay = {"order": order, "word_bytes": wb, "endian": endian, "encoding": enc}
    fmt = ("ci" if cplx else "i") + f"{bits}packed"
    (tmp_path / "x.bin.json").write_text(json.dumps({"format": fmt, "fs_hz": 2e6, "if_hz": 0.0 if cplx else 5e5,
                                                     "packing": lay}))
    levels = PackedLayout(bits=bits, encoding=enc).levels()[codes]
    want = levels[0::2] + 1j * levels[1::2] if cplx else levels
    with open_if(p) as src:
        assert src.n_samples == want.size
        np.testing.assert_array_equal(src.read(0, want.size), want.astype(src.read(0, 1).dtype))
        np.testing.assert_array_equal(src.read(3, 11), want[3:14])
    # our packer agrees with the reference one
    assert PackedLayout(bits, order, wb, endian, enc).pack(codes) == p.read_bytes()


def test_4bit_formats_are_read_only(tmp_path):
    from ultratight.errors import FormatError
    from ultratight.signals.recording.iffile import IfWriter
    with pytest.raises(FormatError, match="read only"):
        IfWriter(tmp_path / "x", "i4packed", 2e6)


def test_other_front_end_layout_acquires_like_ours(tmp_path):
    """A generated 2-bit file re-packed as LSB-first, 16-bit big-endian words, offset binary: read
    with those flags it gives the same acquisitions as the original (CLI, --json)."""
    r = subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", "generate", "static-open-sky", "--duration",
                        "0.6", "--fs", "4e6", "--if", "1.0e6", "--format", "i2packed", "--out", str(tmp_path / "g"),
                        "--no-progress", "--json"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    files = json.loads(r.stdout)["files"]
    src = open_if(files["if"])
    ours = PackedLayout(2)
    levels = src.read(0, src.n_samples)
    other = PackedLayout(2, "lsb-first", 2, "big", "offset-binary")
    (tmp_path / "other.bin").write_bytes(other.pack(other.codes_of_levels(levels)))
    assert ours.encoding == "sign-magnitude"
    res = {}
    for name, args in (("ours", [files["if"]]),
                       ("other", [str(tmp_path / "other.bin"), "--fs", "4e6", "--if", "1e6", "--format", "i2packed",
                                  "--packing", "lsb-first", "--word-size", "2", "--endian", "big",
                                  "--encoding", "offset-binary"])):
        r = subprocess.run([sys.executable, "-m", "ultratight.receiver.cli", "process", *args, "--duration", "0.5",
                            "--json", "--no-progress"], capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr
        res[name] = json.loads(r.stdout)["acquired"]
    assert res["ours"] and res["ours"] == res["other"]


@pytest.mark.parametrize("quant,packed,fmt,enc", [(2, 2, "IF", "TC"), (2, 4, "IQ", "OB"), (4, 4, "IF", "SM"),
                                                  (4, 8, "IQ", "TC"), (1, 2, "IF", "SIGN")])
def test_ion_xml_encodings(tmp_path, quant, packed, fmt, enc):
    """The ION XML's <encoding> (and 2/4-bit width) selects the layout; samples byte-packed, first
    in the high bits."""
    from test_iffile import ION_XML
    is_c = fmt == "IQ"
    bits = packed // 2 if is_c else packed
    name = {"TC": "twos-complement", "OB": "offset-binary", "SM": "sign-magnitude", "SIGN": "sign"}[enc]
    rng = np.random.default_rng(quant * 10 + packed)
    codes = rng.integers(0, 1 << bits, size=8 * 16)
    (tmp_path / "d.bin").write_bytes(_pack_reference(codes, bits, "msb-first", 1, "little"))
    xml = tmp_path / "d.xml"
    xml.write_text(ION_XML.format(quant=quant, packed=packed, fmt=fmt, enc=enc, endian="Little",
                                  if_khz=0 if is_c else 1000, url="d.bin"))
    lv = PackedLayout(bits=bits, encoding=name).levels()[codes]
    want = lv[0::2] + 1j * lv[1::2] if is_c else lv
    with open_if(meta=xml) as src:
        assert src.fmt == ("ci" if is_c else "i") + f"{bits}packed" and src.packing.encoding == name
        np.testing.assert_array_equal(src.read(0, want.size), want.astype(src.read(0, 1).dtype))
