"""An FFT segment with no data (a long gap) is left out of the analysis grid and the gated data.

A live window of 25 h over the blind week's 7-h gap: of its four 6-h FFT segments one lay
wholly in the gap.  The rule keeps a segment holding at least ``MIN_KEPT`` of its taper's
power; measured against the samples the data hold (none), 0 >= 0.6 x 0 kept it, its zeros
scaled by 1e150, and the window refit read chi2/dof 16080 and advised two glitches at the
gap's end.  The check here is the chi^2 of a gapped day against the instrument noise model
(expectation 1 per degree of freedom), which a kept empty segment moves.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ttlcore.diagnose.diagnoser import refit
from ttlcore.diagnose.gating import MIN_KEPT, gated_data, missing_data
from ttlcore.diagnose.settings import DiagnoseSettings
from ttlcore.diagnose.whitened import whiten_telemetry
from ttlcore.sim.simulator import SimulationConfig, simulate

HOURS = 8.0


@pytest.fixture(scope="module")
def gapped_day():
    tm, truth = simulate(SimulationConfig(duration=HOURS * 3600.0, orbit="keplerian", seed=7))
    t = tm.t0 + np.arange(tm.size) / tm.fs
    hole = (t >= 2.5 * 3600) & (t < 6.0 * 3600)  # 3.5 h of missing data: more than one FFT segment
    nan = np.where(hole, np.nan, 1.0)
    gapped = replace(tm, eta=tm.eta * nan, dws_phi=tm.dws_phi * nan, dws_eta=tm.dws_eta * nan)
    return gapped, truth["coefficients"].mean(axis=1), (2.5 * 3600, 6.0 * 3600)


def test_a_segment_inside_a_gap_is_left_out(gapped_day):
    tm, _, (a, b) = gapped_day
    data = whiten_telemetry(tm, DiagnoseSettings(segment_duration=3600.0))
    gaps = missing_data(data)
    assert len(gaps) == 1 and gaps[0][0] <= a + 200 and gaps[0][1] >= b - 200, gaps
    gated = gated_data(data, [], gaps)
    L = data.grid.L / data.grid.fs
    for grid in (data.grid, gated.grid):  # every segment kept holds data for MIN_KEPT of its taper
        for t0 in grid.seg_t0:
            inside = max(0.0, min(t0 + L, b) - max(t0, a))
            assert inside < (1 - MIN_KEPT) * L, (t0, inside)
    # 8 h less the 3.5-h gap and its edges: at most 4 of the 1-h segments, none in the gap
    assert 2 <= len(gated.grid.starts) <= 4, gated.grid.seg_t0


def test_a_gapped_day_reads_one_per_degree_of_freedom(gapped_day):
    tm, C, _ = gapped_day
    fit = refit(tm, ["linear-ttl"], settings=DiagnoseSettings(segment_duration=3600.0)).fit
    # the linear model is the truth here: chi2/dof is 1 within the statistical 1 % of ~3 h of
    # kept data and the noise model's 2 % tolerance; empty segments kept read ~0.6
    assert abs(fit.chi2_dof - 1.0) < 0.03, fit.chi2_dof
    z = np.abs(fit.ttl_coefficients() - C) / fit.ttl_sigma()
    assert z.max() < 4.0, z


def test_an_event_in_a_gaps_ramps_is_the_gap():
    from ttlcore.diagnose.excess import gap_of
    from ttlcore.effects.gate import GATE_TAPER

    gaps = [(422037.5, 447237.25)]  # the blind week's gap
    hop = 225.0
    # the week's "glitch" event, 124.36-124.61 h: 460 s after the gap's end, inside its 900-s ramp
    assert gap_of(447700.0, 448600.0, gaps, hop) == gaps[0]
    assert gap_of(421000.0, 421500.0, gaps, hop) == gaps[0]  # before its start, in the ramp
    # beyond the ramp and a hop: an event of its own
    assert gap_of(447237.25 + GATE_TAPER + hop + 1.0, 460000.0, gaps, hop) is None
    assert gap_of(100.0, 200.0, [], hop) is None
