"""``erva map``: road maps from recorded drives (build, info, compare); road estimate accuracy."""

import math
import os

from erva_ros.commands._common import (add_json_option, add_params_option, bag_warner,
                                       positive_float, positive_int, print_json)
from erva_ros.core.errors import CLIError
from erva_ros.core.roadmap import MapError, MapUnreachable

COMMAND = 'map'
HELP = ('road maps from recorded HIL drives, in a file or on a PostgreSQL server: build, '
        'sync, info, compare, fetch, migrate, roles, bench; the road estimate\'s accuracy')
DESCRIPTION = """\
The road at the tyre is estimated from what the ECU measures (an EKF with the road as a
state, smoothed over a recorded drive); drives over one route are fused into a map keyed
by distance along the route (docs/road.md).

  erva map build BAG... --out MAP   smooth each drive's road estimate and add it to MAP
                                    (created if missing; a new drive adds to an existing
                                    map without the old ones)
  erva map sync MAP BAG|DIR...      add the drives not yet in MAP (recorded offline)
  erva map info MAP                 route, extent, drives, gaps, variance
  erva map compare MAP --road ...   the map against a known road (simulation)
  erva map fetch MAP --end M        a route section into the local cache (as erva run does)
  erva map migrate MAP NEW          copy a map, file <-> server, value for value
  erva map roles MAP --vehicle ID   a fleet's roles on the server: vehicles add and read
  erva map bench                    writers, rebuild and fetch timed, SQLite and server
  erva map accuracy                 the road estimator's error on ISO 8608 A-D and the
                                    paper road, at the shipped sensor noise

BAG is a session bag of a HIL run (erva run --ecu virtual ...): it needs
/erva/ecu/measurements and the distance (/erva/road/estimate, else /erva/road/height).
MAP is an SQLite file, or a PostgreSQL map: postgresql://[USER@]HOST[:PORT]/DATABASE
(libpq's PG* environment and ~/.pgpass fill in what the URI leaves out; a password is
never printed).  Many vehicles may add to one map at once.  Bad input (a bag without the
HIL topics, another route, a corrupt or locked map, a server that refuses) stops with one
line and exit status 2; the map is then unchanged."""


def add_arguments(parser):
    sub = parser.add_subparsers(dest='map_command', metavar='ACTION')
    sub.required = True
    p = sub.add_parser('build', help='add recorded drives to a map (created if missing)',
                       description='Read each bag, run the road estimator over its ECU '
                                   'measurements and smooth it (RTS), high-pass the road, '
                                   'register it on the map (cross-correlation: odometry '
                                   'offset and scale) and fuse it by inverse variance.  All '
                                   'bags are read and checked before the map is written; the '
                                   'bags are added in one transaction (all or none).')
    p.add_argument('bags', nargs='+', metavar='BAG', help='HIL session bags (directories or '
                                                          '.mcap files)')
    p.add_argument('--out', required=True, metavar='MAP',
                   help='the map: an SQLite file or a postgresql:// URI')
    p.add_argument('--route', default=None, metavar='NAME',
                   help='name of a new map\'s route (default: from the first bag\'s session)')
    p.add_argument('--grid', type=positive_float, default=0.1, metavar='M',
                   help='a new map\'s grid spacing in m (default 0.1)')
    p.add_argument('--highpass', type=positive_float, default=6.0, metavar='M',
                   help='a new map\'s high-pass: std of the removed local mean, m (default 6)')
    p.add_argument('--search', type=positive_float, default=3.0, metavar='M',
                   help='registration: odometry error searched, ± m (default 3)')
    p.add_argument('--vehicle', default='', metavar='ID', help='vehicle id stored with the drives')
    add_params_option(p)
    add_json_option(p)
    p = sub.add_parser('sync', help='add the drives not yet in a map (recorded offline)',
                       description='Every HIL session bag given, or found one level under a '
                                   'directory given, whose drive is of the map\'s route and '
                                   'not yet in the map (by its digest) is added, each in its '
                                   'own transaction: what was added stays added.  Bags that '
                                   'are no HIL drive, of another route or already in the map '
                                   'are counted and left alone.  Exit 0: every pending drive '
                                   'added; 1: some refused (one line each); 2: the map cannot '
                                   'be reached (nothing changed: run it again later).')
    p.add_argument('map', metavar='MAP', help='an existing map (file or postgresql:// URI)')
    p.add_argument('bags', nargs='+', metavar='BAG|DIR',
                   help='session bags, or directories of them (e.g. bags/)')
    p.add_argument('--search', type=positive_float, default=3.0, metavar='M',
                   help='registration: odometry error searched, ± m (default 3)')
    p.add_argument('--vehicle', default='', metavar='ID', help='vehicle id stored with the drives')
    add_params_option(p)
    add_json_option(p)
    p = sub.add_parser('fetch', help='a route section of a map into the local cache',
                       description='What erva run --preview map:MAP does before the drive: '
                                   'the section [START, END] m of the map, read in one '
                                   'snapshot, into a local SQLite map that the preview reads '
                                   '(default: the cache erva run uses, under '
                                   '$ERVA_MAP_CACHE_DIR or ~/.cache/erva/maps).')
    p.add_argument('map', metavar='MAP')
    p.add_argument('--start', type=float, default=0.0, metavar='M',
                   help='section start, m along the route (default 0)')
    p.add_argument('--end', type=positive_float, required=True, metavar='M',
                   help='section end, m along the route')
    p.add_argument('--cache', default=None, metavar='FILE',
                   help='write the section here instead of the default cache')
    add_json_option(p)
    p = sub.add_parser('migrate', help='copy a map between a file and a server, value for value',
                       description='Copy every row of MAP (meta, nodes, drives with their ids) '
                                   'into the new map NEW: SQLite to PostgreSQL, back, or the '
                                   'same kind.  NEW must not hold a map yet.  A version-1 file '
                                   'is written as the current version.')
    p.add_argument('map', metavar='MAP', help='the map to copy')
    p.add_argument('new', metavar='NEW', help='the new map (file or postgresql:// URI)')
    add_json_option(p)
    p = sub.add_parser('roles', help='a fleet\'s roles on a server map',
                       description='On the server map MAP (as its owner): the group role '
                                   'GROUP may read the map and add drives (through the '
                                   'function erva_add_drive, which records the role that '
                                   'added each drive) and nothing else: no INSERT, UPDATE or '
                                   'DELETE on any table, so no vehicle can change the fused '
                                   'map or another vehicle\'s drives.  Each --vehicle becomes '
                                   'a login role in GROUP.  Idempotent: run it again to add '
                                   'vehicles.')
    p.add_argument('map', metavar='MAP', help='a postgresql:// map, as its owner')
    p.add_argument('--vehicle', action='append', default=[], metavar='ROLE',
                   help='a vehicle\'s login role (repeat for more)')
    p.add_argument('--group', default='erva_vehicle', metavar='ROLE',
                   help='the vehicles\' group role (default erva_vehicle)')
    p.add_argument('--password-env', default=None, metavar='VAR',
                   help='set each --vehicle\'s password from the environment variable VAR '
                        '(never on the command line); without it, give the roles a password '
                        'as the server\'s administrator prefers (ALTER ROLE ... PASSWORD)')
    add_json_option(p)
    from erva_ros.commands.map_bench import add_bench_parser
    add_bench_parser(sub)
    p = sub.add_parser('info', help='route, extent, drives, gaps and variance of a map')
    p.add_argument('map', metavar='MAP')
    add_json_option(p)
    p = sub.add_parser('compare', help='a map against a known road (simulation)',
                       description='Place the map on the road (its distances are its first '
                                   'drive\'s odometry) and report the error of its detail '
                                   'against the road\'s, high-passed the same way.')
    p.add_argument('map', metavar='MAP')
    p.add_argument('--road', choices=('paper', 'iso8608', 'bump', 'sine'), default='paper',
                   help='the road the drives were on (default paper)')
    p.add_argument('--seed', type=int, default=0, help='its seed (default 0)')
    p.add_argument('--road-class', default='C', choices=list('ABCDE'),
                   help='ISO 8608 class (default C)')
    p.add_argument('--speed', type=positive_float, default=20.0, metavar='M_PER_S',
                   help='the speed the road was generated at (default 20)')
    p.add_argument('--search', type=positive_float, default=3.0, metavar='M',
                   help='± m searched to place the map (default 3)')
    add_json_option(p)
    p = sub.add_parser('accuracy', help='the road estimator\'s error against the true road',
                       description='Drives with the ECU\'s sensors at the shipped noise and a '
                                   'switching damping; the road estimator (filter) and its '
                                   'RTS smoothing against the true road: RMS of the raw error '
                                   '(the offset and drift are not observable) and of its '
                                   'detail (high-passed as the map is).')
    p.add_argument('--roads', default='paper,A,B,C,D', metavar='R[,R...]',
                   help='paper and/or ISO 8608 classes A..D (default paper,A,B,C,D)')
    p.add_argument('--variants', default='shipped', metavar='V[,V...]',
                   help='estimator variants (default shipped; all: every variant, see '
                        'docs/road.md)')
    p.add_argument('--seeds', type=positive_int, default=3, help='drives per road (default 3)')
    p.add_argument('--first-seed', type=int, default=100, metavar='N',
                   help='first road seed (default 100: seeds nothing was tuned on)')
    p.add_argument('--duration', type=positive_float, default=8.0, metavar='S',
                   help='seconds per drive (default 8)')
    add_params_option(p)
    add_json_option(p)


def main(args) -> int:
    from erva_ros.commands.map_bench import bench
    return {'build': _build, 'sync': _sync, 'info': _info, 'compare': _compare,
            'fetch': _fetch, 'migrate': _migrate, 'roles': _roles, 'bench': bench,
            'accuracy': _accuracy}[args.map_command](args)


# -- build ------------------------------------------------------------------------------
def _drive_items(args, bags, road_map, model):
    """Return the DriveItems of ``bags`` (each read, checked and estimated; no map lock)."""
    from erva_ros.core.roadmap.bag_drive import read_bag_drive
    from erva_ros.core.roadmap.drive import estimate_drive, grid_profile
    from erva_ros.core.roadmap.store import DriveItem

    drives = [read_bag_drive(b, warn=bag_warner('erva map build', path=b))
              for b in bags]                              # every bag checked first
    digests = set()
    for d in drives:
        if d.record.digest() in digests:
            raise MapError(f'{d.record.source}: given twice')
        digests.add(d.record.digest())
    route = road_map.route if road_map else (getattr(args, 'route', None)
                                             or drives[0].record.route)
    for d in drives:
        if d.record.route and route and d.record.route != route:
            raise MapError(f'{d.record.source}: drive on route {d.record.route!r}, the map is '
                           f'of route {route!r}')
        if road_map is not None and road_map.has_drive(d.record.digest()):
            raise MapError(f'{d.record.source}: already in the map {road_map.path}')
    grid = road_map.grid_m if road_map else args.grid
    highpass_m = road_map.highpass_m if road_map else args.highpass
    items = []
    for d in drives:
        est = estimate_drive(d.record, model, d.ts)
        items.append(DriveItem(grid_profile(est, grid, highpass_m, ts=d.ts), d.record.digest(),
                               d.record.source, args.vehicle, d.record.route,
                               d.record.speed_mps, args.search))
    return drives, items, route or '', grid, highpass_m


def _build(args) -> int:
    from erva_ros.core.model.quarter_car import make_model
    from erva_ros.core.model.params import load_erva_params
    from erva_ros.core.roadmap.store import add_to_map, RoadMap

    params = load_erva_params(args.params)
    road_map = RoadMap.open(args.out) if RoadMap.exists(args.out) else None
    try:
        drives, items, route, grid, highpass_m = _drive_items(args, args.bags, road_map,
                                                              make_model(params))
    finally:
        if road_map is not None:
            road_map.close()
    road_map, created, regs = add_to_map(args.out, items, route, grid, highpass_m)
    results = [{'bag': d.record.source, 'cycles': len(d.record.t),
                'missing_cycles': d.missing_cycles, 'repeated_cycles': d.repeated_cycles,
                'malformed': d.malformed, 'distance_from': d.distance_topic,
                'offset_m': reg.offset_m, 'scale': reg.scale, 'correlation': reg.correlation,
                'segments': reg.segments} for d, reg in zip(drives, regs)]
    with road_map:
        info = _map_info(road_map)
    out = {'map': road_map.path, 'created': created, 'added': results, 'info': info}
    if args.json:
        print_json(out)
    else:
        for r in results:
            where = ('first drive: defines the distances' if r['segments'] == 0 else
                     f'placed at {r["offset_m"]:+.3f} m, scale {r["scale"] * 100:+.3f} %, '
                     f'correlation {r["correlation"]:.3f} over {r["segments"]} segments')
            print(f'added {r["bag"]}: {r["cycles"]} cycles ({r["missing_cycles"]} missing), '
                  f'{where}')
        _print_info(info)
    return 0


# -- sync ---------------------------------------------------------------------------------
def _bag_paths(args_bags):
    """Return the bags given, and those one level under each directory that is not a bag."""
    out = []
    for path in args_bags:
        if not os.path.exists(path):
            raise CLIError(f'{path}: no such bag or directory')
        if os.path.isdir(path) and not os.path.exists(os.path.join(path, 'metadata.yaml')) \
                and not any(n.endswith('.mcap') for n in os.listdir(path)):
            out += sorted(os.path.join(path, n) for n in os.listdir(path)
                          if os.path.isdir(os.path.join(path, n)) or n.endswith('.mcap'))
        else:
            out.append(path)
    return out


def _sync(args) -> int:
    from erva_ros.core.model.quarter_car import make_model
    from erva_ros.core.model.params import load_erva_params
    from erva_ros.core.roadmap.bag_drive import read_bag_drive
    from erva_ros.core.roadmap.drive import estimate_drive, grid_profile
    from erva_ros.core.roadmap.store import DriveItem, RoadMap

    model = make_model(load_erva_params(args.params))
    paths = _bag_paths(args.bags)
    road_map = RoadMap.open(args.map)
    added, present, skipped, refused = [], [], [], []
    with road_map:
        for path in paths:
            try:
                d = read_bag_drive(path)
            except MapError as exc:
                skipped.append({'bag': path, 'why': str(exc)})
                continue
            rec = d.record
            if rec.route and road_map.route and rec.route != road_map.route:
                skipped.append({'bag': path, 'why': f'route {rec.route!r}'})
                continue
            if road_map.has_drive(rec.digest()):
                present.append(path)
                continue
            try:
                g = grid_profile(estimate_drive(rec, model, d.ts), road_map.grid_m,
                                 road_map.highpass_m, ts=d.ts)
                reg = road_map.add_drives([DriveItem(g, rec.digest(), rec.source, args.vehicle,
                                                     rec.route, rec.speed_mps,
                                                     args.search)])[0]
            except MapUnreachable:
                raise                                    # what was added stays added
            except MapError as exc:
                if 'already in the map' in str(exc):     # another vehicle was quicker
                    present.append(path)
                    continue
                refused.append({'bag': path, 'why': str(exc)})
                continue
            added.append({'bag': path, 'offset_m': reg.offset_m, 'segments': reg.segments})
    out = {'map': road_map.path, 'added': added, 'already_in_map': present,
           'not_drives': skipped, 'refused': refused}
    if args.json:
        print_json(out)
    else:
        for a in added:
            print(f'added {a["bag"]}')
        for r in refused:
            print(f'refused {r["bag"]}: {r["why"]}')
        print(f'{road_map.path}: {len(added)} added, {len(present)} already in the map, '
              f'{len(skipped)} not drives of this map, {len(refused)} refused')
    return 1 if refused else 0


# -- fetch, migrate, roles ----------------------------------------------------------------
def _fetch(args) -> int:
    from erva_ros.core.roadmap.fleet import fetch_section
    if not args.end > args.start:
        raise CLIError(f'--end {args.end:g} m: must be after --start {args.start:g} m')
    f = fetch_section(args.map, args.start, args.end, args.cache)
    if args.json:
        from dataclasses import asdict
        print_json(asdict(f))
    else:
        print(f'{f.source}: {f.start_m:g}..{f.end_m:g} m, {f.nodes} nodes in '
              f'{f.seconds * 1e3:.0f} ms into {f.cache}')
    return 0


def _migrate(args) -> int:
    from erva_ros.core.roadmap.fleet import migrate
    from erva_ros.core.roadmap.location import parse_location
    counts = migrate(args.map, args.new)
    src, dst = parse_location(args.map).display, parse_location(args.new).display
    if args.json:
        print_json({'from': src, 'to': dst, **counts})
    else:
        print(f'{src} -> {dst}: {counts["nodes"]} nodes, {counts["drives"]} drives, '
              f'{counts["meta"]} meta keys, value for value')
    return 0


def _roles(args) -> int:
    from erva_ros.core.roadmap.fleet import grant_roles
    passwords = {}
    if args.password_env:
        secret = os.environ.get(args.password_env)
        if not secret:
            raise CLIError(f'--password-env {args.password_env}: that variable is not set')
        passwords = {v: secret for v in args.vehicle}
    done = grant_roles(args.map, args.group, args.vehicle, passwords)
    if args.json:
        print_json({'group': args.group, 'vehicles': args.vehicle, 'done': done})
    else:
        for line in done:
            print(line)
    return 0


# -- info ---------------------------------------------------------------------------------
DRIVE_KEYS = ('id', 'source', 'vehicle', 'added_utc', 'offset_m', 'scale', 'correlation',
              'speed_mps', 'added_by')


def _map_info(road_map) -> dict:
    import numpy as np
    p = road_map.profile()
    ok = p.valid
    drives = road_map.drives()
    return {'file': road_map.path, 'route': road_map.route, 'schema_version':
            road_map.version, 'grid_m': p.grid_m, 'highpass_m': p.highpass_m,
            'created_utc': road_map.meta.get('created_utc'), 'drives': len(drives),
            'start_m': p.start_m if p.n else None, 'end_m': p.end_m if p.n else None,
            'nodes': int(ok.sum()), 'gaps_m': [list(g) for g in p.gaps()],
            'drives_per_node': {'min': int(p.drives[ok].min()) if ok.any() else 0,
                                'max': int(p.drives[ok].max()) if ok.any() else 0},
            'height_rms_m': float(np.sqrt(np.mean(p.h[ok] ** 2))) if ok.any() else None,
            'std_mean_m': float(np.sqrt(np.mean(p.var[ok]))) if ok.any() else None,
            'variance_scale': p.variance_scale,
            'drive_list': [{k: d.get(k) for k in DRIVE_KEYS} for d in drives]}


def _print_info(info: dict) -> None:
    if info['start_m'] is None:
        print(f'{info["file"]}: empty map (route {info["route"]!r})')
        return
    print(f'map {info["file"]}: route {info["route"] or "(unnamed)"}, {info["drives"]} drives, '
          f'{info["start_m"]:.1f}..{info["end_m"]:.1f} m on a {info["grid_m"]:g} m grid '
          f'({info["nodes"]} nodes, {info["drives_per_node"]["min"]}-'
          f'{info["drives_per_node"]["max"]} drives each)')
    gaps = info['gaps_m']
    print(f'  detail height RMS {info["height_rms_m"] * 1e3:.3f} mm, std '
          f'{info["std_mean_m"] * 1e3:.4f} mm (variance scale {info["variance_scale"]:.3g}), '
          f'high-pass {info["highpass_m"]:g} m; '
          + (f'gaps: {", ".join(f"{a:.1f}-{b:.1f} m" for a, b in gaps)}' if gaps else 'no gaps'))


def _info(args) -> int:
    from erva_ros.core.roadmap.store import RoadMap
    with RoadMap.open(args.map) as road_map:
        info = _map_info(road_map)
    if args.json:
        print_json(info)
    else:
        _print_info(info)
        for d in info['drive_list']:
            print(f'  drive {d["id"]}: {d["source"]} ({d["added_utc"]}), offset '
                  f'{d["offset_m"]:+.3f} m, scale {d["scale"] * 100:+.3f} %')
    return 0


# -- compare ------------------------------------------------------------------------------
def _compare(args) -> int:
    from dataclasses import asdict
    from erva_ros.core.roadmap.store import compare, RoadMap
    from erva_ros.core.roadmap.vehicle import Route
    from erva_ros.core.road.profiles import make_road, RoadError

    with RoadMap.open(args.map) as road_map:
        profile = road_map.profile()
    if not profile.valid.any():
        raise CLIError(f'{args.map}: the map is empty')
    opts = {'road_class': args.road_class} if args.road == 'iso8608' else {}
    duration = (profile.end_m + 50.0) / args.speed
    try:
        road = make_road(args.road, duration, seed=args.seed, speed_mps=args.speed, **opts)
    except RoadError as exc:
        raise CLIError(str(exc)) from None
    route = Route.of(road)
    c = compare(profile, route.height, args.search)
    out = {'map': args.map, 'route': profile.route, 'road': road.name, **asdict(c)}
    if args.json:
        print_json(out)
    else:
        print(f'{args.map} ({profile.route or "unnamed route"}) against {road.name}:')
        print(f'  placed at {c.offset_m:+.3f} m, scale {c.scale * 100:+.3f} %, correlation '
              f'{c.correlation:.3f}, {c.nodes} nodes')
        print(f'  detail error RMS {c.error_rms_m * 1e3:.3f} mm (at the map\'s own distances '
              f'{c.error_rms_unplaced_m * 1e3:.3f} mm); road detail RMS '
              f'{c.road_detail_rms_m * 1e3:.3f} mm; the map\'s own std '
              f'{c.predicted_std_m * 1e3:.4f} mm')
    return 0


# -- accuracy -----------------------------------------------------------------------------
def _accuracy(args) -> int:
    import numpy as np
    from erva_ros.core.model.params import load_erva_params
    from erva_ros.core.roadmap.accuracy import accuracy, ROADS, VARIANTS

    roads = [r.strip() for r in args.roads.split(',') if r.strip()]
    variants = list(VARIANTS) if args.variants == 'all' else \
        [v.strip() for v in args.variants.split(',') if v.strip()]
    for r in roads:
        if r not in ROADS:
            raise CLIError(f'--roads: {r!r}; choose from {", ".join(ROADS)}')
    for v in variants:
        if v not in VARIANTS:
            raise CLIError(f'--variants: {v!r}; choose from {", ".join(VARIANTS)} or all')
    params = load_erva_params(args.params)
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    rows = []
    for v in variants:
        for r in roads:
            runs = [accuracy(params, r, s, v, args.duration) for s in seeds]
            rows.append({'variant': v, 'road': r, 'seeds': list(seeds),
                         **{k: float(np.mean([x[k] for x in runs])) for k in runs[0]},
                         'smoother_detail_max': float(max(x['smoother_detail'] for x in runs))})
    if args.json:
        print_json({'rows': rows})
        return 0
    print(f'road estimate error RMS (mm), mean over seeds {seeds.start}..{seeds.stop - 1}, '
          f'{args.duration:g} s drives at 20 m/s')
    print('| variant | road | road detail | filter detail | smoother detail | filter raw | '
          'smoother raw | predicted std |')
    print('|---|---|---|---|---|---|---|---|')
    for r in rows:
        print(f'| {r["variant"]} | {r["road"]} | {r["road_detail"] * 1e3:.3f} | '
              f'{r["filter_detail"] * 1e3:.3f} | {r["smoother_detail"] * 1e3:.3f} | '
              f'{r["filter_raw"] * 1e3:.2f} | {r["smoother_raw"] * 1e3:.2f} | '
              f'{r["predicted_std"] * 1e3:.3f} |')
    return 0 if all(math.isfinite(r['smoother_detail']) for r in rows) else 1
