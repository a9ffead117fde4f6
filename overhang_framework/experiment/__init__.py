"""The human experiment: the paper's task in the browser, served and logged with the project's own world.

* :mod:`~overhang_framework.experiment.settings` -- ``conf/serve.yaml``, checked;
* :mod:`~overhang_framework.experiment.practice` -- the practice towers a person can build (``python -m ...practice``);
* :mod:`~overhang_framework.experiment.api` -- the FastAPI app (``docs/experiment.md``);
* :mod:`~overhang_framework.experiment.store` -- participants and placements (SQLAlchemy 2);
* :mod:`~overhang_framework.experiment.outcome` -- the world's verdict and the tower's motion;
* :mod:`~overhang_framework.experiment.export` -- the behaviour log of the stored trials;
* :mod:`~overhang_framework.experiment.web` -- the front end's build (``web/``).

    python -m overhang_framework.experiment
"""
