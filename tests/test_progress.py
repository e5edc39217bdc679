"""Progress lines: rewritten in place on a terminal, a few whole lines anywhere else."""

import io

from hybridloc.progress import Progress


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_log_gets_a_line_per_tenth_and_the_end():
    out = io.StringIO()
    bar = Progress("[x] done", 228, out)
    for i in range(1, 229):
        bar.update(i)
    lines = out.getvalue().splitlines()
    assert "\r" not in out.getvalue()
    assert 10 <= len(lines) <= 11  # one per tenth crossed (the first update included), the end once
    assert lines[0] == "[x] done 1/228" and lines[-1] == "[x] done 228/228"


def test_terminal_rewrites_one_line_and_ends_it():
    out = _Tty()
    bar = Progress("[x] done", 3, out, bar_width=3)
    for i in (1, 2, 3):
        bar.update(i, "(dev)")
    assert out.getvalue() == "\r[x] done [#..] 1/3 (dev)\r[x] done [##.] 2/3 (dev)\r[x] done [###] 3/3 (dev)\n"
    bar.close()  # already ended: nothing more
    assert out.getvalue().endswith("3/3 (dev)\n")


def test_nothing_to_do_still_says_so():
    out = io.StringIO()
    Progress("[x] done", 0, out).update(0)
    assert out.getvalue() == "[x] done 0/0\n"
