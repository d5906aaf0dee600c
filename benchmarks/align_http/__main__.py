"""``python -m benchmarks.align_http``: see ``benchmarks.align_http.command``."""

from benchmarks.align_http.command import main

main()
