"""Code the benchmarks share that is no benchmark itself: ``make bench`` runs
``benchmarks/*.py``, never what is in this folder."""
