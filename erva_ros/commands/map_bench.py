"""``erva map bench``: placeholder."""


def add_bench_parser(sub):
    sub.add_parser('bench', help='writers, rebuild and fetch timed')


def bench(args) -> int:
    return 0
