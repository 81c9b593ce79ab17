"""Benchmarks: `erva bench --live`, the recorder, Foxglove and HIL benches, soak."""
