"""gravcald's env-guarded memory probe (daemon/memory_probe.py): what it reports."""
import tracemalloc

from gravcal.daemon import memory_probe


def test_report_names_the_line_holding_memory_and_what_grew():
    memory_probe._FIRST.clear()
    tracemalloc.start(1)
    try:
        first = memory_probe.report()
        held = [bytes(1000) + b"%d" % k for k in range(3000)]  # about 3 MB on this line
        second = memory_probe.report()
    finally:
        tracemalloc.stop()
        memory_probe._FIRST.clear()
    here = f"{__file__}:"
    assert "grown since" not in first and "grown since" in second
    grown = second.split("grown since the first report:")[1]
    line = next(x for x in grown.splitlines() if here in x)
    assert float(line.split()[0]) * 1024 > 0.9 * sum(map(len, held)), line


def test_report_without_tracing_gives_pymalloc_arenas():
    assert not tracemalloc.is_tracing()
    text = memory_probe.report()
    arenas = next(x for x in text.splitlines() if "arenas allocated current" in x)
    assert int(arenas.split("=")[1]) > 0
