"""Shared test helpers: the gravcald child-process runner and the fault and soak campaigns.

The tests call the campaigns at small sizes and assert on their figures; bench/bench_faults.py and
bench/bench_soak.py run the same functions at the issue's sizes and print the figures.
"""
