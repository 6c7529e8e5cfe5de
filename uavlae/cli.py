"""The console scripts of ``pip install uavlae`` (``[project.scripts]`` in pyproject.toml).

Each is the module's own entry point, as ``python -m uavlae.<module>`` runs it: ``uavlae-train``
is ``python -m uavlae.train``, ``uavlae-evaluate`` is ``python -m uavlae.evaluate``, and so on.
The wrappers here are what those ``__main__`` blocks run: a command line holding an API key is
refused before Hydra writes it down, the commands that only read a run write no Hydra folder into
the working directory, and an error the user can fix ends the command with one line
(:func:`uavlae.entry.command`), or ``main`` returns a value that a console script would take
for its exit status.
``uavlae-report`` is :func:`uavlae.experiments.report.main` directly: the library never imports
the experiments layer, not even here.
"""

from __future__ import annotations

import sys


def train() -> None:
    """``uavlae-train +exp=NAME [key=value ...]`` (``python -m uavlae.train``)."""
    from uavlae.entry import command
    from uavlae.llm.config import refuse_secret_overrides
    from uavlae.train import main

    refuse_secret_overrides(sys.argv)  # before Hydra writes the command line into the run folder
    command(main)


def evaluate() -> None:
    """``uavlae-evaluate checkpoint=RUN_DIR [key=value ...]`` (``python -m uavlae.evaluate``)."""
    from uavlae.entry import command
    from uavlae.evaluate import main
    from uavlae.llm.config import refuse_secret_overrides
    from uavlae.runlog import without_hydra_output

    refuse_secret_overrides(sys.argv)  # before Hydra writes the command line down
    sys.argv = without_hydra_output(sys.argv)
    command(main)


def export() -> None:
    """``uavlae-export checkpoint=RUN_DIR out=actor.pt2`` (``python -m uavlae.export``)."""
    from uavlae.entry import command
    from uavlae.export import main
    from uavlae.runlog import without_hydra_output

    sys.argv = without_hydra_output(sys.argv)
    command(main)


def fly() -> None:
    """``uavlae-fly --actor actor.pt2 --scenario scenario.json`` (``python -m uavlae.fly``)."""
    from uavlae.fly import main

    main()


def demo() -> None:
    """``uavlae-demo`` (``python -m uavlae.demo``): the greedy heuristic over sampled scenarios."""
    from uavlae.demo import main

    main()
