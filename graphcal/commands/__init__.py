"""The command layer: one module per ``graphcal`` command, each with one entry point ``run(...)``.

A command reads the files its arguments name, calls the library and writes its outputs; it returns
a frozen result (:mod:`graphcal.commands.result`: the library's result, the files written, the
warnings, the verdict) whose ``summary_text()`` is what the command line prints. :mod:`graphcal.cli`
only parses arguments, calls these and prints that text.
Only this package (and the tests) may import :mod:`graphcal.simulation`.
"""
