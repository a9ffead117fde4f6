"""The likelihood is the simulated participant's own choice rule: its choices, sampled by the simulator's code
with fresh draws, follow the probabilities the likelihood gives (overhang_framework.testing.likelihood)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from overhang_framework.fit.agreement import build_state, rejects
from overhang_framework.fit.choice import BankChoice, ChoiceParams, VerdictBank, fixed_draw_prob, g_test, holm
from overhang_framework.testing.likelihood import ChoiceModelContract

sys.path.insert(0, str(Path(__file__).parent))
from search_fixtures import value, world  # noqa: E402,F401  (the static world and its value)

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bank(world):
    return VerdictBank(world, sigma=0.03, size=200, seed=99)


class _Participant(ChoiceModelContract):
    params: ChoiceParams
    draws = 20_000
    state_names = ("A",)

    @pytest.fixture
    def choice_model(self, world, value, bank):
        return BankChoice(world, value, bank, self.params, draws=self.draws, seed=5)

    @pytest.fixture
    def states(self, world):
        return [build_state(world, name) for name in self.state_names]


class TestMyopicK10(_Participant):
    params = ChoiceParams(depth=1, K=10, beta=8.0)
    state_names = ("A", "C")


class TestOneSimulationAHandAndLapses(_Participant):
    params = ChoiceParams(depth=1, K=1, beta=8.0, lapse=0.1, hand=0.05)


class TestRiskAverseCvar(_Participant):
    params = ChoiceParams(depth=1, K=50, beta=12.0, risk=0.3, risk_form="cvar")
    state_names = ("C",)


class TestDepthTwoRiskAverse(_Participant):
    params = ChoiceParams(depth=2, K=10, beta=8.0, risk=0.5, lapse=0.05)
    choices = 800
    draws = 8_000
    state_names = ("B",)


class TestPercept(_Participant):
    params = ChoiceParams(depth=1, K=10, beta=8.0, percept=0.04)
    choices = 1_200
    draws = 6_000


class TestHybridAtDepthTwo(_Participant):
    """The IPE judges the towers of 3 blocks, the CNN those of 4: both parts in one search."""
    params = ChoiceParams(depth=2, K=10, beta=8.0, switch=4)
    choices = 800
    draws = 6_000


class TestPaperLikePerson(_Participant):
    """The CNN with a planned hand, a percept, risk and lapses (the paper's people under time pressure)."""
    params = ChoiceParams(depth=1, K=50, beta=8.0, switch=3, hand=0.13, percept=0.03, risk=0.9, lapse=0.07)
    choices = 500
    draws = 1_500


def test_the_hybrid_sends_each_tower_to_its_part(world, value, bank):
    """Towers below the switch point are the bank's IPE's (they vary with the draws), the others the CNN's (the same
    under every draw, and the CNN's own answers)."""
    state = build_state(world, "A")  # 2 blocks: its children have 3
    actions = world.legal_actions(state)
    early = BankChoice(world, value, bank, ChoiceParams(depth=1, K=10, switch=4))._answers(state, actions)
    late_choice = BankChoice(world, value, bank, ChoiceParams(depth=1, K=10, switch=3))
    late = late_choice._answers(state, actions)
    assert np.array_equal(early, bank.verdicts(state, actions).astype(float))
    assert np.ptp(late, axis=1).max() == 0 and np.ptp(early, axis=1).max() > 0
    cnn = late_choice.late().predict(state, actions, np.random.default_rng(0))
    assert np.allclose(late[:, 0], cnn)


def test_the_fixed_draw_likelihood_of_the_score_tables_fails_the_same_test(world, value, bank):
    """The likelihood with one fixed draw of the noise per node (the fit's score tables before the participant's
    own noise entered them) is rejected on every state where the marginal one is kept, at the suite's size."""
    states = [build_state(world, name) for name in ("A", "C")]
    model = BankChoice(world, value, bank, ChoiceParams(depth=1, K=10, beta=8.0), draws=20_000, seed=5)
    kept, _ = rejects(model, states, 3000, 0.01, 1)
    old, results = rejects(model, states, 3000, 0.01, 1, prob=lambda s: fixed_draw_prob(model, s, seed=3))
    assert not any(kept) and all(old), [r.p for r in results]


def test_one_simulation_at_depth_one_is_exact_the_average_over_the_banks_draws(world, value, bank):
    state = build_state(world, "A")
    params = ChoiceParams(depth=1, K=1, beta=8.0, lapse=0.2)
    model = BankChoice(world, value, bank, params)
    actions = world.legal_actions(state)
    verdicts = bank.verdicts(state, actions).astype(float)  # (n, B)
    reach = np.array([world.overhang(world.step(state, a).geometry) for a in actions])
    scores = verdicts.T * reach
    soft = np.exp(8.0 * (scores - scores.max(axis=1, keepdims=True)))
    expected = 0.8 * (soft / soft.sum(axis=1, keepdims=True)).mean(axis=0) + 0.2 / len(actions)
    assert np.allclose(model.prob(state), expected, rtol=0, atol=1e-12)
    assert not model.prob_error(state).any()


def test_the_likelihood_does_not_depend_on_the_seed_beyond_its_reported_monte_carlo_error(world, value, bank):
    state = build_state(world, "A")
    params = ChoiceParams(depth=2, K=10, beta=8.0)
    a = BankChoice(world, value, bank, params, draws=8000, seed=1)
    b = BankChoice(world, value, bank, params, draws=8000, seed=2)
    gap = np.abs(a.prob(state) - b.prob(state))
    se = np.hypot(a.prob_error(state), b.prob_error(state))
    assert np.all(gap <= 5 * se + 1e-12), (gap.max(), se.max())
    assert a.prob_error(state).max() < 0.005


def test_the_g_test_and_holm_give_the_textbook_answers():
    assert g_test(np.array([25, 25, 50]), np.array([0.25, 0.25, 0.5]))[2] == pytest.approx(1.0)
    g, dof, p = g_test(np.array([40, 10, 50]), np.array([0.25, 0.25, 0.5]))
    assert dof == 2 and g == pytest.approx(2 * (40 * np.log(40 / 25) + 10 * np.log(10 / 25)))
    assert g_test(np.array([1, 99]), np.array([0.0, 1.0]))[2] == 0.0  # an impossible choice was made
    assert holm([0.001, 0.02, 0.04, 0.5], 0.05) == [True, False, False, False]
    assert holm([0.01, 0.012, 0.013], 0.05) == [True, True, True]


def test_the_agreement_command_writes_its_report_and_continues_a_stopped_run(tmp_path):
    out = tmp_path / "agreement"
    first = subprocess.run([sys.executable, "-m", "overhang_framework.fit.agreement", "--out", str(out), "--quick",
                            "--only", "0"], capture_output=True, text=True, cwd=REPO)
    assert first.returncode == 0, first.stderr
    assert "case 0 (A, D1, K10, beta 8)" in first.stdout
    rest = subprocess.run([sys.executable, "-m", "overhang_framework.fit.agreement", "--out", str(out), "--quick"],
                          capture_output=True, text=True, cwd=REPO)
    assert rest.returncode == 0, rest.stderr
    assert "case 0 " not in rest.stdout and "case 1 " in rest.stdout and "case 2 " in rest.stdout
    text = (out / "agreement.md").read_text()
    assert "- **The likelihood** (the participant's own noise marginalised) is rejected for 0 of all 3 cases" in text
    assert "- **The fixed-draw likelihood** (one draw of the noise per node, as the fit's score tables gave) is " \
           "rejected for 3 of them" in text
    bad = subprocess.run([sys.executable, "-m", "overhang_framework.fit.agreement", "--out", str(out), "--quick",
                          "--only", "9"], capture_output=True, text=True, cwd=REPO)
    assert bad.returncode == 2 and "--only takes case numbers from 0 to 2" in bad.stderr


def test_a_bank_that_forgets_its_oldest_nodes_gives_the_same_verdicts_when_asked_again(world):
    small = VerdictBank(world, sigma=0.03, size=50, seed=4, max_rows=30)
    whole = VerdictBank(world, sigma=0.03, size=50, seed=4)
    states = [build_state(world, name) for name in ("A", "B", "C")]
    first = [small.verdicts(s, world.legal_actions(s)) for s in states]
    assert small._held <= 30 + max(len(world.legal_actions(s)) for s in states)  # the oldest nodes went
    again = [small.verdicts(s, world.legal_actions(s)) for s in states]
    for a, b, s in zip(first, again, states):
        assert np.array_equal(a, b) and np.array_equal(a, whole.verdicts(s, world.legal_actions(s)))
