"""Input/output: log files, wire protocols (pure encode/decode) and device drivers."""
