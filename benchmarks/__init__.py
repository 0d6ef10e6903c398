"""jtraj benchmarks (makes ``benchmarks.peers`` importable from the repo root)."""
