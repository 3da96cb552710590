"""The benchmark scripts (``bench_<topic>.py``, run as scripts or by ``sonarloc bench``)
and the helpers they share, imported as ``benchmarks._machine`` with the repository root
on ``sys.path`` (a package, so no other ``benchmarks`` on the path can shadow it)."""
