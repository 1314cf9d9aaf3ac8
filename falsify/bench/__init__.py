"""Benchmarks behind `falsify bench`: each fast path measured beside its naive path, or beside
the machine's own rate, in one run. Speed claims live here, never in timed unit tests; each
benchmark returns a typed result whose `to_json()` is what --json prints.
"""
