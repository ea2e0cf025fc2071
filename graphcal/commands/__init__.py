"""The command layer: one module per ``graphcal`` command, each with one entry point ``run(...)``.

A command reads the files its arguments name, calls the library and writes its outputs; it returns
the summary the command line prints. :mod:`graphcal.cli` only parses arguments and calls these.
Only this package (and the tests) may import :mod:`graphcal.simulation`.
"""
