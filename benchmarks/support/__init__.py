"""What the benchmarks and tests share and the shipped package does not: experiment runners, paper worlds."""
