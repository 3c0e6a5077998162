"""What runs, measures and feeds the services: the `aesop` command, `aesop up`, the demo,
the benchmarks, recordings, the synthetic scenes and the fake LLM."""
