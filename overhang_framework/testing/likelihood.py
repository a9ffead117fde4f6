"""The contract between a model's simulation and its likelihood: the choices it samples are drawn with the
probabilities its likelihood gives.

A *choice model* is any object with ``world`` (the world its states are of), ``sample(state, rng)`` (the index in
``world.legal_actions(state)`` of the action the simulated agent chooses, drawing everything it draws from
``rng``) and ``prob(state)`` (the probability of each of those actions, the likelihood a fit uses). The built-in
one is :class:`overhang_framework.fit.choice.BankChoice`. A plugin proves that its likelihood is its
simulation's by subclassing the suite in its own tests::

    from overhang_framework.testing.likelihood import ChoiceModelContract

    class TestMyPlannersLikelihood(ChoiceModelContract):
        choices = 5000

        @pytest.fixture
        def choice_model(self):
            return MyChoiceModel(...)

        @pytest.fixture
        def states(self, choice_model):
            return [...]

For each state the suite samples ``choices`` choices with fresh draws and compares their frequencies with
``prob`` by a G-test (:func:`overhang_framework.fit.choice.g_test`), with Holm's correction over the states
at family-wise level ``alpha``.
"""

from __future__ import annotations

import numpy as np
import pytest

from overhang_framework.fit.agreement import agreement
from overhang_framework.fit.choice import holm


class ChoiceModelContract:
    """Provide ``choice_model`` and ``states``; set ``choices`` (per state), ``alpha`` and ``seed`` to taste."""

    choices: int = 3000
    alpha: float = 0.01
    seed: int = 20261202

    def test_prob_is_a_distribution_over_the_legal_actions(self, choice_model, states):
        for state in states:
            probs = np.asarray(choice_model.prob(state), dtype=float)
            assert probs.shape == (len(choice_model.world.legal_actions(state)),)
            assert np.all(probs >= 0) and probs.sum() == pytest.approx(1.0, abs=1e-9)

    def test_sampled_choices_are_drawn_with_the_likelihoods_probabilities(self, choice_model, states):
        results = [agreement(choice_model, state, self.choices, np.random.default_rng([self.seed, k]))
                   for k, state in enumerate(states)]
        rejected = holm([r.p for r in results], self.alpha)
        report = "; ".join(f"state {k}: G = {r.g:.1f} on {r.dof} df, p = {r.p:.2g}"
                           for k, r in enumerate(results))
        assert not any(rejected), f"the sampled choices do not follow prob (Holm, alpha {self.alpha}): {report}"
