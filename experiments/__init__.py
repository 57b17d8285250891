"""The benchmarks and measurements behind docs/ and experiments/results/.

Each module is one experiment (``sweep``, ``byte_budget``, ``lossy_links``,
...) or a helper they share (``common``, ``stats``, ``matrix_time``).  Run an
experiment from the repository's root, with the project's virtualenv::

    .venv/bin/python -m experiments.NAME --help
    sudo .venv/bin/python -m experiments.sweep --profile quick --jobs 2

The ones that emulate links (network namespaces) need root, as the module's
docstring and ``--help`` say.  Results go to ``experiments/results/``, which
holds data, not code.  This package is not installed with ``coapkb``: it runs
from a checkout.
"""
