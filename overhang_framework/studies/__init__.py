"""Planted, null and graded studies: ``python -m overhang_framework.study {dual_transition,null,paper_calibrated,paper_people,graded_budgets}
--out DIR``.

The package, one module a job: :mod:`~overhang_framework.studies.findings` (the participant table and the
findings tested on it), :mod:`~overhang_framework.studies.power` (studies redrawn from the participants, and the
share in which a finding holds), :mod:`~overhang_framework.studies.gather` (simulations made already, taken as one
study), :mod:`~overhang_framework.studies.run` (the steps, each continued where it stopped),
:mod:`~overhang_framework.studies.report` (``study.md``), :mod:`~overhang_framework.studies.graded` (the graded
study's predictions, trends and design) and :mod:`~overhang_framework.studies.command` (the command line).

Can the whole pipeline find the paper's dual transition where it is present, and not find it where
it is absent? A study simulates a cohort of known participants, analyses their log as a lab would
analyse people's, fits the models, checks the fits, and reports the paper's findings one by one:

* ``dual_transition`` (``cohort=dual_transition``, ``predictor=hybrid``): the paper's hypothesis by
  construction. Every participant is a hybrid (the IPE below its own switch point, the CNN from it on);
  both conditions intend the same searches (depth 1 or 2), and the 5 s budget truncates the time-limited
  ones. Each finding below should be there.
* ``null`` (``cohort=null_effect``, ``predictor=ipe``): one predictor family, no switch, and the same
  myopic search in both conditions, which the budget never truncates. None should be there, beyond chance.
* ``paper_calibrated`` (``cohort=paper_calibrated``, ``predictor=hybrid``): people like the paper's, each
  condition's distributions of depth, σ, β, lapse and decision time fitted to the paper's Table 1 and Γ
  (:mod:`overhang_framework.behaviour.calibrate`; docs/fidelity.md says which it matches and which not).
  A fit of one family (the others deleted from the fit's ``models``) leaves the family finding untested,
  and says so.
* ``paper_people`` (``cohort=paper_people``, which names its own predictor, the hybrid): the paper's people
  with the axes of docs/people.md (risk aversion, a hand planned for, perceptual noise), each condition
  calibrated to the paper's Table 1 and Γ by direct simulation.
* ``graded_budgets`` (``cohort=graded_budgets``): those people under four time limits between subjects, the
  study the paper calls for. Its findings are each level's figures and the trends across the levels, with the
  participants per level a lab needs for 80% power (:mod:`overhang_framework.studies.graded`); the steps are the same.

The steps, each continued where it stopped when the command is run again with the same settings:
``sim/`` (:mod:`overhang_framework.behaviour.simulation`), ``analysis/`` (Table 1, Γ, Fig. 4 of
:mod:`overhang_framework.analyze`), ``fit/`` (:mod:`overhang_framework.fit`, the default model space with
the hybrid's switch point fitted, score tables in ``scores.sqlite``), then ``study.md``, ``findings.csv``,
``power.csv`` and ``participants.csv`` (one row per participant: every quantity a finding tests), and last
``fit/check/`` (:mod:`overhang_framework.fit.check`, the study's own participants, not the pool's others),
whose first finding ``study.md`` then adds.

Participants simulated already (say, each condition's run at the paper's size, made sitting by sitting) are
taken as they are with ``--sim DIR`` (once per run directory; each must be a finished simulation of the
study's cohort, or of another whose participants are the study's people condition by condition
(:func:`population`); no participant may appear twice, and no two runs may draw their participants from
the same random streams, i.e. the same seed, since participant ``i`` of a seed draws from the same streams in
every run): ``sim/`` then holds their logs and tables, the study proper is all of them, and power is a
bootstrap of them. A graded study's 5 s and no-limit levels are ``cohort=paper_people``'s two conditions, so
its runs serve there, and only the other levels need simulating::

    python -m overhang_framework.participants cohort=graded_budgets seed=10 \
        'cohort.participants={limit_2_5s: 40, time_limited: 0, limit_10s: 40, unconstrained: 0}' hydra.run.dir=runs/graded_new
    python -m overhang_framework.study graded_budgets --out runs/graded --sim runs/graded_new \
        --sim runs/pp_tl --sim runs/pp_un        # the paper_people runs at seeds of their own, e.g. 1 and 0

People's data (an export of the study: JSON Lines, CSV or a Psych-DS folder) are analysed the same way with
``--log LOG``: ``people/`` then holds their log, power is a bootstrap of them, and the report opens with what the
study's size cannot support (:func:`overhang_framework.studies.graded.verdict`)::

    python -m overhang_framework.study graded_budgets --log runs/graded-export.jsonl --out runs/graded-people

``--no-fit`` leaves out the fit (and the predictive
check); the findings of the fit (depth, hybrid, switch) are then reported as not tested::

    python -m overhang_framework.study paper_people --out runs/pp_study --sim runs/pp_tl --sim runs/pp_un --no-fit

The findings (:data:`FINDINGS`), each a test across participants at ``alpha = .05``:

1. ``overhang``: lower average overhang under time pressure (permutation test, Table 1);
2. ``stable``: no difference in the stable proportion (permutation test; holds when p >= alpha);
3. ``gamma``: Γ lower under time pressure (permutation test);
4. ``vertical``: placements nearer the centre under time pressure, Fig. 3a's "vertical stacking" (each
   participant's mean |x| of their placements from step 3 on, :func:`overhang_framework.behaviour.flows.lateral`;
   permutation test);
5. ``baseline``: both approximate models beat the veridical one on the executed placements (Fig. 4: each
   participant's mean ``LL_ipe - LL_veridical`` and ``LL_cnn - LL_veridical``, one-sample t-tests; holds when
   both are above 0 at p < alpha);
6. ``crossover``: the CNN overtakes the IPE as blocks accumulate (each participant's mean ``LL_cnn - LL_ipe``
   on towers of at least :data:`LATE` blocks minus that on towers of at most :data:`EARLY`; one-sample t-test);
7. ``depth``: the fitted depth (of each participant's best model by BIC) lower under time pressure
   (permutation test);
8. ``hybrid``: the hybrid family wins: random-effects BMS over families (each family's evidence the
   log-mean-exp of its models' ``-BIC/2``), protected exceedance probability above 0.95;
9. ``switch``: the fitted switch point near the planted one: among participants whose best model is a
   hybrid, the mean absolute difference at most one stage (planted study only).

A directional finding holds when its two-sided p is below ``alpha`` and the difference goes the paper's way,
so a null study shows it by chance at most ``alpha / 2`` of the time.

The study proper is the cohort's size (``--scale`` times the paper's 43 + 38): the first participants of
each condition. **Power and false positives.** Each participant's simulation, analysis and fit are their
own, so a study of the same size can be redrawn by resampling participants. ``--pool 2`` (the default)
simulates twice as many participants, and ``--resamples`` studies of the cohort's size are drawn from them
without replacement. The share of redrawn studies in which a finding holds is its power (planted) or its
false-positive rate (null). With ``--pool 1`` the draws are with replacement from the study's own
participants: a bootstrap, which gives the rate of the effect this sample happens to show (optimistic), and
the report says so. Where the planted power is below 0.8, larger studies are redrawn (1.5 to 8 times the
size; with replacement once they outgrow the pool, so optimistic) and the smallest that reaches 0.8 is
reported.
"""
