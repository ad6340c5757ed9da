"""Outside data through the pipeline: a lisainstrument measurement file replayed by ``ttl run``.

lisainstrument (a test dependency) writes a two-hour measurement file; ``ttl run
--telemetry`` replays it in 30-minute segments (the last one shorter) through the five stage processes.  The
replayer's telemetry must equal our reader's eta variables of the file (the ingest runs in
the replayer), the streamed TDI must equal the batch TDI of the same telemetry, and every
stage must handle every segment.
"""

from __future__ import annotations

import numpy as np
from lisainstrument_sim import simulate_lisainstrument
from ttl_testutil import MONITOR, OUTPUT, STAGES, Procs, finish, indices, output, run_args

from streamer.recording.recorder import read_recording


def test_lisainstrument_file_replayed_through_the_pipeline(tmp_path):
    from ttlcore.io.reader import read_telemetry
    from ttlcore.io.telemetry import Telemetry
    from ttlcore.tdi.data import compute_tdi

    li = tmp_path / "measurements.h5"
    simulate_lisainstrument(li, duration=2 * 3600 + 600, orbits="static", seed=5)  # margin for its t0 handling
    procs = Procs(tmp_path)
    try:
        proc = procs.ttl(
            *run_args("li", tmp_path / "rec", telemetry=li, segment="30min", timeout=300),
            "--adopt",
            "never",  # the file's way through the stages; the live diagnosis is tests/test_live_loop.py's
            *([] if MONITOR else ["--skip", "monitor"]),
        )
        code = finish(proc, 300)
    finally:
        procs.close()
    assert code == 0, output(proc)[-5000:]
    run = tmp_path / "rec" / "li"
    tel = sorted(read_recording(run / "replayer.mcap").segments("telemetry"), key=lambda s: s.header.index)
    total = tel[0].header.meta["segments_total"]
    assert total == 5  # 2 h 10 min in 30-min segments, the last one short
    for stage in STAGES:
        rec = read_recording(run / f"{stage}.mcap")
        assert rec.complete and rec.json("errors") == [], (stage, rec.json("errors"))
        assert ("complete", total - 1) in [(e["kind"], e["index"]) for e in rec.json("events")], stage
        # every segment gets its fit, the short last one too (its FFT segment is closed with a
        # gap, RollingFit.flush)
        assert sorted(indices(rec, OUTPUT[stage])) == list(range(total)), stage

    # the replayed telemetry is our reader's view of the lisainstrument file
    assert tel[0].header.meta["source"] == str(li.resolve())
    replayed = Telemetry(
        t0=tel[0].header.t0,
        fs=4.0,
        **{k: np.concatenate([s.arrays[k] for s in tel], axis=1) for k in ("eta", "dws_phi", "dws_eta", "ltt")},
    )
    direct = read_telemetry(li)
    n0 = int(round((replayed.t0 - direct.t0) * direct.fs))
    np.testing.assert_array_equal(replayed.eta, direct.eta[:, n0 : n0 + replayed.size])
    np.testing.assert_array_equal(replayed.dws_phi, direct.dws_phi[:, n0 : n0 + replayed.size])

    # streamed TDI equals the batch TDI of the same telemetry
    tdi = sorted(read_recording(run / "tdi_builder.mcap").segments("tdi"), key=lambda s: s.header.index)
    batch = compute_tdi(replayed)
    # to 1e-9 of the largest sample (streamed and batch TDI cut the engine's blocks at different places)
    np.testing.assert_allclose(
        np.concatenate([s.arrays["data"] for s in tdi], axis=1),
        batch.data,
        rtol=1e-9,
        atol=1e-9 * np.nanmax(np.abs(batch.data)),
    )
    # the last fit (2 h window) sees the lisainstrument default coefficients' TTL: finite, converged
    last = read_recording(run / "fitter.mcap").segments("fit")[-1]
    assert np.all(np.isfinite(last.arrays["coefficients"])) and last.header.meta["converged"]
    # the last segment holds 10 min less the reduction's 49 samples: its 30-min FFT segment is
    # less than half valid, so the window's fit stands for it, flagged as a gap
    assert last.header.index == total - 1 and last.header.meta["excluded"]["gap"] is True
