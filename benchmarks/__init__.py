"""jtraj benchmarks (scripts; their reference peers are the top-level ``jtraj_peers``)."""
