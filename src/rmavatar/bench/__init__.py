"""Benchmarks behind ``rmavatar bench NAME`` (options: ``rmavatar.commands.bench``)."""
