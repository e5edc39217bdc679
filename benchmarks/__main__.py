"""Run every benchmark: ``python -m benchmarks`` (``make bench``)."""

from . import bench_foot_ins, bench_phone_pdr

if __name__ == "__main__":
    bench_phone_pdr.main([])
    bench_foot_ins.main([])
