"""The lab's engines, shared by the benchmarks and their tests: the in-process evaluation
of a recorded run (``evaluation``) and the crash trials against a server process
(``crash_trials``). Not part of the wheel: the product never imports them."""
