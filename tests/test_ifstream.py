"""The generator's IF streamed into the receiver (ultratight.signals.synth.ifstream.GeneratedIf): the samples
of the IF file ``generate`` writes for the same configuration and seed, bit for bit, in every
front-end variant; reads in any order; memory held independent of the run's length; and the
scenario's methods on the streamed IF give exactly the results they give on the cached file."""

import threading

import numpy as np
import pytest

from ultratight.receiver.cli.scenario_config import load_scenario
from ultratight.signals.synth.generator import generate
from ultratight.signals.recording.iffile import open_if
from ultratight.signals.synth.ifstream import GeneratedIf, HeldBytes

SHORT = {"duration_s": 0.35, "frontend.fs_hz": 2.046e6, "satellites.max_count": 3}

# front ends: fixed-gain int16 with a noise burst inside the cut (the paper scenario), AGC int8,
# real IF with spectral inversion and a band-pass filter (state carried across blocks), 2-bit
# packed complex and real with inversion, and sample counts that do not fill the last block/byte
VARIANTS = {
    "ci16-fixed-burst": ("paper-highdyn", {}, [{"t0_s": 0.12, "t1_s": 0.21, "noise_factor": 20.0}]),
    "ci8-agc-lowpass": ("static-open-sky", {"frontend.filter_bw_hz": 1.5e6}, None),
    "i8-real-inverted-bandpass": ("static-open-sky", {
        "frontend.sampling": "real", "frontend.format": "i8", "frontend.bits": 8, "frontend.fs_hz": 8.184e6,
        "frontend.if_hz": 2.1e6, "frontend.inversion": True, "frontend.filter_bw_hz": 2.5e6,
        "duration_s": 0.2503}, None),
    "ci2packed-inverted-odd": ("static-open-sky", {
        "frontend.format": "ci2packed", "frontend.bits": 2, "frontend.inversion": True, "duration_s": 0.3005}, None),
    "i2packed-real": ("static-open-sky", {
        "frontend.sampling": "real", "frontend.format": "i2packed", "frontend.bits": 2, "frontend.fs_hz": 4.092e6,
        "frontend.if_hz": 1.023e6, "duration_s": 0.2001}, None),
}


def _cfg(name):
    scen, ov, events = VARIANTS[name]
    cfg = load_scenario(scen, {**SHORT, **ov})
    if events is not None:
        cfg["noise_events"] = events
    return cfg


def _same(a, b):
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a.view(np.uint8), b.view(np.uint8))


@pytest.mark.parametrize("name", list(VARIANTS))
def test_streamed_samples_equal_the_file(tmp_path, name):
    cfg = _cfg(name)
    paths = generate(cfg, tmp_path, "g", seed=5, progress=False)
    f = open_if(paths["if"])
    with GeneratedIf(cfg, 5) as g:
        for k in ("fs_hz", "if_hz", "is_complex", "n_samples", "start_week", "start_tow_s"):
            assert getattr(g, k) == getattr(f, k), k
        rng = np.random.default_rng(1)
        pos = 0
        while pos < f.n_samples:           # irregular reads across block and byte boundaries
            n = int(rng.integers(1, 90001))
            assert _same(g.read(pos, n), f.read(pos, n)), (name, pos, n)
            pos += n
        assert g.read(f.n_samples, 10).shape == (0,)
        assert g.restarts == 0
    f.close()


def test_reading_back_regenerates_the_same_samples(tmp_path):
    cfg = _cfg("ci16-fixed-burst")
    paths = generate(cfg, tmp_path, "g", seed=2, progress=False)
    f = open_if(paths["if"])
    for threaded in (True, False):
        with GeneratedIf(cfg, 2, threaded=threaded, keep_s=0.01) as g:
            assert _same(g.read(300_000, 200_000), f.read(300_000, 200_000))
            assert g.restarts == 0
            assert _same(g.read(1000, 5000), f.read(1000, 5000))     # dropped: generated again
            assert g.restarts == 1
        with GeneratedIf(cfg, 2, threaded=threaded, keep_s=1.0) as g:
            assert _same(g.read(0, 700_000), f.read(0, 700_000))
            assert _same(g.read(500_000, 100_000), f.read(500_000, 100_000))    # still held
            assert g.restarts == 0
            assert g.release(600_000) == 4 * 600_000                      # no longer needed (ci16)
            assert _same(g.read(500_000, 100_000), f.read(500_000, 100_000))
            assert g.restarts == 1
    f.close()


def test_memory_held_does_not_grow_with_length():
    cfg = load_scenario("static-open-sky", {"duration_s": 2.0, "frontend.fs_hz": 2.046e6,
                                            "satellites.max_count": 2})
    n_before = threading.active_count()
    g = GeneratedIf(cfg, 1, keep_s=0.05)
    blk = 20460                            # the engine's 10 ms reads
    peak = 0
    for pos in range(0, g.n_samples, blk):
        g.read(pos, blk)
        peak = max(peak, g.held_bytes())
    # held: the kept 50 ms, the read and at most one 100 ms generator block beyond it (2 bytes a sample)
    assert peak <= 2 * (int(0.05 * g.fs_hz) + blk + int(0.1 * g.fs_hz) + 1)
    g.close()
    assert threading.active_count() == n_before        # the generator thread has ended


def test_streamed_methods_equal_cached(tmp_path, monkeypatch):
    """dlb-rackf and the scalar reference on the streamed IF: bit-identical to the cached file's run."""
    from ultratight.receiver.cli import scenario_runner as SR
    cfg = load_scenario("paper-highdyn", {"duration_s": 1.0, "frontend.fs_hz": 2.046e6, "satellites.max_count": 3})
    streamed, cached_flag = SR.prepare_data(cfg, 4, tmp_path, cache_if=False)
    assert not cached_flag and "if" not in streamed and streamed["if_seed"] == 4
    assert not list((tmp_path / "cache").glob("*/*.ci16"))     # no IF file written
    cached, _ = SR.prepare_data(cfg, 4, tmp_path, cache_if=True)
    assert cached["if"].is_file() and cached["truth"] == streamed["truth"]
    sources = []
    real_open = SR.open_source
    monkeypatch.setattr(SR, "open_source", lambda p, c: sources.append(real_open(p, c)) or sources[-1])
    for m in ("dlb-rackf", "scalar"):
        a, _ = SR.run_method(streamed, cfg, m, 4)
        b, _ = SR.run_method(cached, cfg, m, 4)
        assert isinstance(sources[-2], GeneratedIf) and sources[-2].restarts == 0
        for k in ("t_start", "doppler_hz", "code_phase_chips", "amp", "mode", "nav_t", "nav_pos_e", "nav_vel_e",
                  "nav_clk"):
            x, y = np.asarray(getattr(a, k)), np.asarray(getattr(b, k))
            assert x.shape == y.shape and np.array_equal(x, y, equal_nan=True), (m, k)
        assert a.t_start.shape[0] > 900


def test_scenario_command_streams_by_default_and_caches_on_request(tmp_path, capsys):
    """``ultratight scenario`` without ``--cache`` writes no IF file and reports exactly the figures of
    the same run with ``--cache`` (which keeps the IF file in OUT/cache)."""
    import json

    from ultratight.receiver.cli import main
    figures = {}
    for flag in ([], ["--cache"]):
        out = tmp_path / ("cached" if flag else "streamed")
        rc = main(["scenario", "paper-highdyn", "--duration", "1.2", "--fs-hz", "2.046e6", "--methods",
                   "dlb-ckf,scalar", "--workers", "1", "--json", "--no-plots", "--out", str(out), *flag])
        cap = capsys.readouterr()
        assert rc == 0, cap.err
        files = [p for p in out.rglob("*") if p.is_file()]
        if_files = [p for p in files if p.name.endswith(".ci16")]
        assert len(if_files) == (1 if flag else 0)
        if not flag:
            assert max(p.stat().st_size for p in files) < 10e6
        js = json.loads(cap.out)["methods"]
        for m in js:
            for k in ("runtime_s", "realtime_factor"):
                js[m].pop(k)
        figures[bool(flag)] = js
    assert figures[False] == figures[True]
    assert np.isfinite(figures[False]["dlb-ckf"]["doppler_rms_hz"][0])


def test_campaign_run_streams_unless_cached(tmp_path):
    """The campaign's IF-level run (``if_double_loop.run_one``) streams by default and writes the IF
    file with ``cache=True``, with the same metrics; ``--cache`` is refused for other experiments."""
    from ultratight.errors import ConfigError
    from ultratight.receiver.cli.campaign import run_campaign
    from ultratight.receiver.cli import if_double_loop as X
    cfg = X.load("paper-highdyn", {}, {"duration_s": 0.8, "frontend.fs_hz": 2.046e6, "satellites.max_count": 3})
    got = {}
    for cache in (False, True):
        out = tmp_path / str(cache)
        res = X.run_one(X.with_data_dir(cfg, out, cache=cache), ["scalar", "dlb-rackf"], 6)
        assert len(list(out.glob("cache/*/*.ci16"))) == (1 if cache else 0)
        for m in res["methods"].values():
            m.pop("runtime_s"), m.pop("realtime_factor")
        got[cache] = res
    import json
    same = json.dumps(got[False]["methods"], sort_keys=True, default=repr)     # NaN (no segment) included
    assert same == json.dumps(got[True]["methods"], sort_keys=True, default=repr)
    for m in ("scalar", "dlb-rackf"):
        assert np.array_equal(got[False]["series"][m]["doppler_err_hz"], got[True]["series"][m]["doppler_err_hz"],
                              equal_nan=True)
    with pytest.raises(ConfigError, match="--cache"):
        run_campaign("paper-afm-jump", runs=1, out_dir=tmp_path / "afm", cache=True, progress=False)


def test_held_bytes_spans_and_drops_like_one_array():
    # the chunked store against the one concatenated array it replaces: random chunk sizes (empty ones
    # too), drops inside and across chunks, spans inside one chunk (a view) and across several (a copy)
    # (every chunk appended, empty ones included, is either held or counted once as let go: a ring
    # reader tells its producer a slot is free by that count)
    rng = np.random.default_rng(3)
    held, flat, base = HeldBytes(), np.zeros(0, np.uint8), 0
    appended = gone = 0
    for _ in range(400):
        op = rng.integers(3)
        if op == 0:
            c = rng.integers(0, 256, int(rng.integers(0, 50)), dtype=np.uint8)
            held.append(c)
            appended += 1
            flat = np.concatenate([flat, c])
        elif op == 1:
            nb = int(rng.integers(0, flat.size + 1))
            gone += held.drop(nb)
            flat, base = flat[nb:], base + nb
            assert gone + held.count() == appended
        elif flat.size:
            b0 = int(rng.integers(0, flat.size + 1))
            b1 = int(rng.integers(b0, flat.size + 1))
            got = held.span(b0, b1)
            assert got.dtype == np.uint8 and np.array_equal(got, flat[b0:b1]), (base, b0, b1)
            parts = held.parts(b0, b1)
            assert np.array_equal(np.concatenate(parts) if parts else flat[:0], flat[b0:b1])
        assert held.size == flat.size


@pytest.mark.parametrize("fmt", ["ci16", "ci8", "i16", "i8"])
def test_decoding_from_parts_equals_decoding_their_concatenation(fmt):
    """A read whose samples lie in two held chunks is decoded part by part (``decode_parts``) instead of
    from the joined bytes: the same float32 values, for any cut of the parts and any sample range."""
    from ultratight.signals.recording.iffile import get_format
    spec = get_format(fmt)
    rng = np.random.default_rng(7)
    info = np.iinfo(spec.dtype)
    for _ in range(200):
        n = int(rng.integers(1, 400))
        comps = rng.integers(info.min, info.max, n * spec.comps, endpoint=True).astype(spec.dtype)
        cuts = np.sort(rng.integers(0, n + 1, int(rng.integers(0, 4)))) * spec.comps
        parts = np.split(comps, cuts)
        start = int(rng.integers(0, n))
        count = int(rng.integers(0, n - start + 1))
        want = spec.decode(comps, start, count)
        got = spec.decode_parts(parts, start, count)
        assert got.dtype == want.dtype == np.float32 and np.array_equal(got, want)
