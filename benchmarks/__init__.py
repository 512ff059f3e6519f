"""The lab: A/B benchmarks and studies, outside the wheel (benchmarks/README.md)."""
