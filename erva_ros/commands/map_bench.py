"""``erva map bench``: a fleet's map, timed -- writers at once, a rebuild, a route fetch."""

import os
import shutil
import subprocess
import tempfile
import time
import uuid
from urllib.parse import urlsplit, urlunsplit

from erva_ros.commands._common import add_json_option, positive_float, positive_int, print_json
from erva_ros.commands._jobs import add_jobs_options, run_jobs
from erva_ros.core.errors import CLIError

DESCRIPTION = """\
N synthetic drives (core/roadmap/bench.py: the paper road of one seed as a route of L km,
a survey drive that defines its distances, then N drives of D km at seeded places with
odometry bias and scale errors and the road estimator's error, calibrated by running the
estimator) are added to a new map by 1, 2, 4 writer processes at once, one transaction
per drive: in an SQLite file and, with --server, on PostgreSQL.  Then the whole map is
rebuilt from the drives and their stored registrations as independent jobs (--jobs local
processes or a Dask cluster, --scheduler), and a route section of --fetch-km is fetched
into a local cache --fetches times.  Prints drives/s, p50/p99/max of the per-drive add
and of its write transaction, with the sample counts, and the load (uptime) before and
after: the machine may be shared, so the timings are a benchmark, not a promise."""


def add_bench_parser(sub) -> None:
    p = sub.add_parser('bench', help='a fleet\'s map timed: writers at once, rebuild, fetch',
                       description=DESCRIPTION)
    p.add_argument('--drives', type=positive_int, default=1000, metavar='N',
                   help='drives added (default 1000)')
    p.add_argument('--route-km', type=positive_float, default=20.0, metavar='L',
                   help='route length in km (default 20)')
    p.add_argument('--drive-km', type=positive_float, default=1.0, metavar='D',
                   help='length of each drive in km (default 1)')
    p.add_argument('--writers', default='1,2,4', metavar='W[,W...]',
                   help='writer processes at once (default 1,2,4)')
    p.add_argument('--server', default=None, metavar='URI',
                   help='a PostgreSQL server (postgresql://...) on which this role may '
                        'create databases: one per run, dropped after (default: SQLite only)')
    p.add_argument('--fetch-km', type=positive_float, default=1.0, metavar='KM',
                   help='the route section fetched (default 1 km)')
    p.add_argument('--fetches', type=positive_int, default=20, metavar='R',
                   help='fetches timed (default 20)')
    p.add_argument('--seed', type=int, default=0, help='route and drives seed (default 0)')
    add_jobs_options(p, 'share of the rebuild\'s drives')
    add_json_option(p)


def _writers(text: str):
    try:
        ws = sorted({int(w) for w in text.split(',') if w.strip()})
    except ValueError:
        raise CLIError(f'--writers {text!r}: expected counts separated by commas') from None
    if not ws or any(w < 1 or w > 16 for w in ws):
        raise CLIError(f'--writers {text!r}: each between 1 and 16')
    return ws


def _load() -> str:
    try:
        out = subprocess.run(['uptime'], capture_output=True, text=True, timeout=5).stdout
        return out.strip().split('load average:')[-1].strip()
    except (OSError, subprocess.SubprocessError):
        return 'unknown'


class _Server:
    """Databases for the bench on a PostgreSQL server: one per map, dropped at the end."""

    def __init__(self, uri: str):
        from erva_ros.core.roadmap.backends import _psycopg
        self.psycopg = _psycopg()
        self.uri = uri
        self.made = []
        try:
            self.admin = self.psycopg.connect(uri, autocommit=True, connect_timeout=5)
        except self.psycopg.Error as exc:
            from erva_ros.core.redact import redact
            raise CLIError(f'--server {redact(uri)}: cannot connect ({exc})'.splitlines()[0]
                           ) from None

    def new(self) -> str:
        name = f'erva_bench_{uuid.uuid4().hex[:10]}'
        self.admin.execute(f'CREATE DATABASE {name}')
        self.made.append(name)
        p = urlsplit(self.uri)
        return urlunsplit((p.scheme, p.netloc, '/' + name, p.query, ''))

    def close(self) -> None:
        for name in self.made:
            self.admin.execute(f'DROP DATABASE IF EXISTS {name} WITH (FORCE)')
        self.admin.close()


def bench(args) -> int:
    import numpy as np
    from erva_ros.core.roadmap import bench as B
    from erva_ros.core.roadmap.fleet import fetch_section
    from erva_ros.core.redact import redact
    from erva_ros.core.roadmap.store import RoadMap

    writers = _writers(args.writers)
    if args.drive_km + 0.1 >= args.route_km:
        raise CLIError(f'--drive-km {args.drive_km:g}: must be shorter than --route-km '
                       f'{args.route_km:g} by 0.1 km')
    if args.fetch_km >= args.route_km:
        raise CLIError(f'--fetch-km {args.fetch_km:g}: must be shorter than the route')
    load_before = _load()
    say = (lambda *a: None) if args.json else (lambda *a: print(*a, flush=True))
    t0 = time.perf_counter()
    err_std, var = B.calibrate(args.seed)
    fleet = B.Fleet(args.route_km, args.drives, args.drive_km, args.seed,
                    error_std_m=err_std, var_m2=var)
    say(f'erva map bench: {args.drives} drives of {args.drive_km:g} km on {args.route_km:g} '
        f'km; estimator error {err_std * 1e3:.3f} mm, variance {var:.3g} m² (calibrated, '
        f'{time.perf_counter() - t0:.0f} s); load {load_before}')
    B.truth(fleet)
    server = _Server(args.server) if args.server else None
    tmp = tempfile.mkdtemp(prefix='erva_map_bench_')
    rows, fetch, rebuild = [], [], None
    try:
        backends = ['sqlite'] + (['postgresql'] if server else [])
        last = {}
        for backend in backends:
            for w in writers:
                loc = server.new() if backend == 'postgresql' else \
                    os.path.join(tmp, f'w{w}.db')
                t = time.perf_counter()
                with RoadMap.create(loc, fleet.route_name, fleet.grid_m, fleet.highpass_m) as m:
                    m.add(B.survey(fleet), B.digest(fleet, -1), 'survey')
                survey_s = time.perf_counter() - t
                r = B.run_writers(fleet, loc, w)
                r.update(backend=backend, survey_s=survey_s)
                rows.append(r)
                last[backend] = loc
                say(_row_line(r))
            fetch.append(_fetch(fleet, backend, last[backend], args.fetch_km, args.fetches,
                                os.path.join(tmp, f'cache_{backend}.db'), fetch_section))
            say(f'  fetch {args.fetch_km:g} km from {backend}: ' + _stats_ms(fetch[-1]['s']))
        target = server.new() if server else os.path.join(tmp, 'rebuilt.db')
        rebuild = _rebuild(fleet, last[backends[-1]], backends[-1], args, B, np, target)
        say(f'  rebuild ({rebuild["jobs"]} jobs, {rebuild["where"]}): sums '
            f'{rebuild["sums_s"]:.1f} s, write {rebuild["write_s"]:.1f} s, '
            f'max relative difference to the incremental map {rebuild["max_rel_diff"]:.1e}')
    finally:
        if server:
            server.close()
        shutil.rmtree(tmp, ignore_errors=True)
    out = {'drives': args.drives, 'route_km': args.route_km, 'drive_km': args.drive_km,
           'seed': args.seed, 'estimator_error_std_m': err_std, 'estimator_var_m2': var,
           'server': redact(args.server) if args.server else None, 'rows': rows,
           'fetch': fetch, 'rebuild': rebuild, 'load_before': load_before,
           'load_after': _load(), 'elapsed_s': time.perf_counter() - t0}
    if args.json:
        print_json(out)
    else:
        print(markdown(out), end='')
    return 0


def _fetch(fleet, backend, loc, km, reps, cache, fetch_section):
    import numpy as np
    rng = np.random.default_rng(fleet.seed + 99)
    times = []
    for _ in range(reps):
        start = rng.uniform(0, fleet.route_km - km) * 1e3
        f = fetch_section(loc, start, start + km * 1e3, cache)
        times.append(f.seconds)
    from erva_ros.core.roadmap.bench import stats
    return {'backend': backend, 'km': km, 's': stats(times), 'nodes': f.nodes}


def _rebuild(fleet, loc, backend, args, B, np, target):
    """Rebuild the map at ``loc`` from its drives' stored registrations; check and time it."""
    from erva_ros.core.roadmap.store import RoadMap
    with RoadMap.open(loc) as m:
        drives = m.drives()
        inc = np.array(m.db.execute('SELECT i, info, info_height FROM nodes ORDER BY i'))
    regs = []
    for d in drives:
        k = int(d['digest'].rsplit('-', 1)[1]) if d['source'] != 'survey' else -1
        regs.append((k, d['offset_m'], d['scale'], d['origin_m']))
    n_jobs = max(1, min(len(regs), (args.jobs or 2) * 4))
    jobs = [(fleet, regs[j::n_jobs]) for j in range(n_jobs)]
    t = time.perf_counter()
    parts = run_jobs(B.rebuild_job, jobs, args.jobs, args.scheduler)
    lo = parts[0][0]
    info = sum(p[1] for p in parts)
    ih = sum(p[2] for p in parts)
    cnt = sum(p[3] for p in parts)
    sums_s = time.perf_counter() - t
    ok = cnt > 0
    idx = np.flatnonzero(ok)
    t = time.perf_counter()
    with RoadMap.create(target, fleet.route_name, fleet.grid_m, fleet.highpass_m) as m:
        m.db.begin_write(10.0)
        m.db.copy_rows('nodes', ('i', 'info', 'info_height', 'drives'), zip(
            (idx + lo).tolist(), info[ok].tolist(), ih[ok].tolist(), cnt[ok].tolist()))
        m.db.commit()
    write_s = time.perf_counter() - t
    same = inc.shape[0] == idx.size and np.array_equal(inc[:, 0].astype(int), idx + lo)
    rel = float(np.max(np.abs(np.c_[info[ok], ih[ok]] - inc[:, 1:]) / np.maximum(
        np.abs(inc[:, 1:]), 1e-300))) if same else float('inf')
    return {'backend': backend, 'jobs': n_jobs, 'where': f'Dask {args.scheduler}'
            if args.scheduler else f'{args.jobs or "all"} local processes',
            'sums_s': sums_s, 'write_s': write_s, 'nodes': int(idx.size), 'max_rel_diff': rel}


def _stats_ms(s) -> str:
    return (f'p50 {s["p50"] * 1e3:.1f} / p99 {s["p99"] * 1e3:.1f} / max {s["max"] * 1e3:.1f} '
            f'ms ({s["samples"]} samples)')


def _row_line(r) -> str:
    return (f'  {r["backend"]}, {r["writers"]} writer(s): {r["drives_per_s"]:.1f} drives/s; '
            f'add {_stats_ms(r["add_s"])}; write transaction {_stats_ms(r["write_s"])}; '
            f'{r["retries"]} retries, {r["registered_again"]} registered under the lock')


def markdown(out) -> str:
    """Return the bench's table (docs/road.md shows it)."""
    lines = [f'{out["drives"]} drives of {out["drive_km"]:g} km on a {out["route_km"]:g} km '
             f'route; load {out["load_before"]} before, {out["load_after"]} after; '
             f'{out["elapsed_s"]:.0f} s', '',
             '| database | writers | drives/s | add p50 / p99 / max (ms) | write transaction '
             'p50 / p99 / max (ms) | retries | samples |', '|---|---|---|---|---|---|---|']
    for r in out['rows']:
        a, w = r['add_s'], r['write_s']
        lines.append(f'| {r["backend"]} | {r["writers"]} | {r["drives_per_s"]:.1f} | '
                     f'{a["p50"] * 1e3:.0f} / {a["p99"] * 1e3:.0f} / {a["max"] * 1e3:.0f} | '
                     f'{w["p50"] * 1e3:.1f} / {w["p99"] * 1e3:.1f} / {w["max"] * 1e3:.1f} | '
                     f'{r["retries"]} | {a["samples"]} |')
    lines += ['', '| fetch of a route section | p50 / p99 / max (ms) | nodes | samples |',
              '|---|---|---|---|']
    for f in out['fetch']:
        s = f['s']
        lines.append(f'| {f["backend"]}, {f["km"]:g} km | {s["p50"] * 1e3:.1f} / '
                     f'{s["p99"] * 1e3:.1f} / {s["max"] * 1e3:.1f} | {f["nodes"]} | '
                     f'{s["samples"]} |')
    rb = out['rebuild']
    if rb:
        lines += ['', f'Rebuild from the {out["drives"] + 1} drives\' stored registrations '
                  f'({rb["jobs"]} jobs, {rb["where"]}): node sums {rb["sums_s"]:.1f} s, bulk '
                  f'write {rb["write_s"]:.1f} s, {rb["nodes"]} nodes, max relative difference '
                  f'to the incremental map {rb["max_rel_diff"]:.1e}']
    return '\n'.join(lines) + '\n'
