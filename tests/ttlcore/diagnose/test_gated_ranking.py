"""The choice between candidates scored on the gated data (:mod:`ttlcore.diagnose.gated_ranking`):
the numbers against the chi^2 quantile and the tolerance written out here."""

from scipy import stats

from ttlcore.diagnose.gated_ranking import GatedRanking, complexity, reordered, simplest_alike

PLAIN = {"cli_spec": "witness:source=31.phi,link=31,delay=2", "n_parameters": 1, "delta_chi2": 9000.0}
RESONANCE = {
    "cli_spec": "fd-coupling:source=31.phi,delay=2,f0=0.00718Hz,q=47.1",
    "n_parameters": 1,
    "delta_chi2": 12000.0,
    "searched": {"search": {"estimates": {"f0": 0.00718, "q": 47.1}}},
}
STEP = {"cli_spec": "step:t_step=8h", "n_parameters": 24, "delta_chi2": 5000.0, "searched": {"t_step": 28800.0}}


def test_complexity_counts_the_searched_parameters():
    assert complexity(PLAIN) == 1 and complexity(RESONANCE) == 3 and complexity(STEP) == 25


def test_the_plain_coupling_wins_when_the_shape_adds_less_than_the_tolerance():
    # on the gated data the resonance takes 8000, the plain witness 7900: 100 short, less than
    # 2 % of 8000 (160) and more than chi2.isf(1e-3, 2) = 13.8: alike, the simpler wins
    assert stats.chi2.isf(1e-3, 2) < 100 < 0.02 * 8000
    scored = [(RESONANCE, 8000.0, 3990.0), (PLAIN, 7900.0, 3945.0), (STEP, 2000.0, 900.0)]
    chosen, d = simplest_alike(scored, 1e-3, 0.02)
    assert chosen is PLAIN and d == 7900.0


def test_a_shape_the_data_need_is_kept():
    # the plain witness 300 short of the resonance's 8000: more than 2 % (160) - the shape is needed
    scored = [(RESONANCE, 8000.0, 3990.0), (PLAIN, 7700.0, 3845.0)]
    chosen, _ = simplest_alike(scored, 1e-3, 0.02)
    assert chosen is RESONANCE
    # with little excess the chi2 quantile decides: 10 short of 300 is within 13.8 for 2 parameters
    chosen, _ = simplest_alike([(RESONANCE, 300.0, 140.0), (PLAIN, 290.0, 140.0)], 1e-3, 0.02)
    assert chosen is PLAIN
    chosen, _ = simplest_alike([(RESONANCE, 300.0, 140.0), (PLAIN, 280.0, 135.0)], 1e-3, 0.02)
    assert chosen is RESONANCE


def test_reordered_puts_the_chosen_first_with_its_gated_score():
    ranking = GatedRanking(
        spans=((22500.0, 31500.0),),
        scores=(
            {"cli_spec": RESONANCE["cli_spec"], "complexity": 3, "delta_chi2": 12000.0, "delta_chi2_gated": 8000.0},
            {"cli_spec": PLAIN["cli_spec"], "complexity": 1, "delta_chi2": 9000.0, "delta_chi2_gated": 7900.0},
        ),
        chosen=PLAIN["cli_spec"],
        reason="explains the gated data alike",
    )
    out = reordered([RESONANCE, PLAIN, STEP], ranking)
    assert [c["cli_spec"] for c in out] == [PLAIN["cli_spec"], RESONANCE["cli_spec"], STEP["cli_spec"]]
    assert out[0]["delta_chi2_gated"] == 7900.0 and "delta_chi2_gated" not in out[2]
    assert ranking.to_json()["spans"] == [[22500.0, 31500.0]]
