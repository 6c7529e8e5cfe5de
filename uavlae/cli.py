"""The console scripts of ``pip install uavlae`` (``[project.scripts]`` in pyproject.toml).

Each is the module's own entry point, as ``python -m uavlae.<module>`` runs it: ``uavlae-train``
is ``python -m uavlae.train``, ``uavlae-evaluate`` is ``python -m uavlae.evaluate``, and so on.
The wrappers here exist where a module's ``__main__`` block does more than call ``main`` (the
commands that only read a run write no Hydra folder into the working directory), or where
``main`` returns a value that a console script would take for its exit status.
``uavlae-report`` is :func:`uavlae.experiments.report.main` directly: the library never imports
the experiments layer, not even here.
"""

from __future__ import annotations

import sys


def evaluate() -> None:
    """``uavlae-evaluate checkpoint=RUN_DIR [key=value ...]`` (``python -m uavlae.evaluate``)."""
    from uavlae.evaluate import main
    from uavlae.runlog import without_hydra_output

    sys.argv = without_hydra_output(sys.argv)
    main()


def export() -> None:
    """``uavlae-export checkpoint=RUN_DIR out=actor.pt2`` (``python -m uavlae.export``)."""
    from uavlae.export import main
    from uavlae.runlog import without_hydra_output

    sys.argv = without_hydra_output(sys.argv)
    main()


def fly() -> None:
    """``uavlae-fly --actor actor.pt2 --scenario scenario.json`` (``python -m uavlae.fly``)."""
    from uavlae.fly import main

    main()


def demo() -> None:
    """``uavlae-demo`` (``python -m uavlae.demo``): the greedy heuristic over sampled scenarios."""
    from uavlae.demo import main

    main()
