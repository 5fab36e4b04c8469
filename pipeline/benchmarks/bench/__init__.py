"""`relight bench`: every relighting method over its parameter sweep, against the reference.

methods.py      the adapter protocol, `BenchScene` and the registry of methods (one name each)
measure.py      baking a grid point and relighting it under every light edit -> SweepRows
references.py   reference renders, once per (scene, light edit, bounce count, spp), cached on disk
comparison.py   the path tracer at equal time and at equal PSNR (MSE ~ 1/spp fit), the speed-ups
chart.py        speed_accuracy.png and params_<method>.png
runner.py       `run_bench`: scenes x methods -> bench.csv, bench.json, summary.txt, charts
stability.py    the stability suite (cases where each method fails) and docs/STABILITY.md
the methods' adapters live beside their bakes: pipeline/bake/<method>/adapter.py
"""
