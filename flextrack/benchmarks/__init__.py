"""Benchmarks that print figures (`flextrack bench NAME`); not tests."""
