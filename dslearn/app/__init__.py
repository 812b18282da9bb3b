"""The ``dslearn-run`` application, in rooms by role. Its entry point is :mod:`dslearn.run`: the console
script (:func:`dslearn.run.main`) and the Hydra task it starts, which runs :func:`dslearn.app.job.run_job`.

* :mod:`dslearn.app.common`: what the rooms share: the program's name, the config folder, the status
  file, the one line on stderr, and the state :func:`dslearn.run.main` hands to the Hydra task;
* :mod:`dslearn.app.options`: the command line read before anything is composed: overrides parsed,
  group options, launchers and output folders checked, "did you mean" hints, Hydra's errors in one line;
* :mod:`dslearn.app.composer`: every job of a sweep composed cheaply and validated
  (:func:`~dslearn.app.composer.check_jobs`), the sweep's combinations and its sweeper's choice;
* :mod:`dslearn.app.precheck`: the start-up check of a whole command line and a single run's folder lock;
* :mod:`dslearn.app.record`: one run's work and its files (:func:`~dslearn.app.record.execute`:
  ``config.yaml``, ``meta.json``, ``results.csv``; ``status.json``), the warnings it counts;
* :mod:`dslearn.app.job`: one job in its locked folder: resume, failures, Ctrl-C, its status;
* :mod:`dslearn.app.help`: ``--help``, ``--version`` and the shell completion answered without composing;
* :mod:`dslearn.app.endings`: how a command ends when interrupted (one line, an interrupted sweep's
  resume command) or after matrix cells failed (exit 1).

Start-up cost: the rooms import only the standard library, OmegaConf and dslearn's light root modules at
module level, so that ``--help``, ``--version``, a refused option and a completion request answer at once;
Hydra, pandas and the schemas (which import PyTorch, GPyTorch and numba) are imported where work starts
(``benchmarks/startup.py`` measures it; ``tests/test_startup.py`` keeps it so).
"""

import warnings

# known harmless third-party warnings (set before gpytorch is imported anywhere):
# gpytorch 1.11+ decorates with torch.jit.script, which torch >= 2.5 marks deprecated
warnings.filterwarnings("ignore", message=r".*torch\.jit\.script.* is deprecated", category=DeprecationWarning)
warnings.filterwarnings("ignore", message=r".*torch\.jit\.script.* is deprecated", category=FutureWarning)
