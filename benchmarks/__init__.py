"""Benchmarks (not tests: no timing assertions). ``python -m benchmarks.run`` (``make bench``)
runs all of them on one fixed simulated workload and writes ``benchmarks/results/latest.json``
and ``latest.md``; the single-topic scripts (``render_vs_mujoco``, ``contact_speed``,
``depth_fidelity``, ``depth_quantisation``) also run on their own."""
