"""The loop process: what runs in the real-time process, and nothing else of the daemon (its
modules, and the shared ones below it that it imports: :mod:`jtc_hw.daemon`'s docstring).
Nothing is imported here.
"""
