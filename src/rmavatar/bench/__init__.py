"""Benchmarks behind ``rmavatar bench NAME`` (see ``rmavatar.bench.cli``)."""
