"""Benchmarks (``python -m benchmarks``): each prints its human lines, then one JSON line of its
headline figures named with their units (``steps_per_s``, ``real_time_factor``...) for scripts and CI."""


def headline(figures: dict) -> None:
    """The benchmark's last line: ``json.dumps`` of its figures (floats to 6 significant digits)."""
    import json
    import math

    def num(v):
        if isinstance(v, (bool, int, str)) or v is None:
            return v
        f = float(v)
        return float(f"{f:.6g}") if math.isfinite(f) else None

    print(json.dumps({k: num(v) for k, v in figures.items()}), flush=True)
