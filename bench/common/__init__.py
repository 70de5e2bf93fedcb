"""Helpers the benchmarks share: the evaluation set and its synthetic scenes, training and evaluating a run,
the pick's measurement, settings on the command line, and where a result comes from.

A script imports them as ``common.<module>``: ``python bench/<script>.py`` puts ``bench/`` on ``sys.path``
(the tests import them through ``tests/script_module.py``). Nothing in ``virgi_ns`` imports them.
"""
