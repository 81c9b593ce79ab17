"""``erva map``: road maps from recorded drives (build, info, compare); road estimate accuracy."""

import math
import os

from erva_ros.commands._common import (add_json_option, add_params_option, bag_warner,
                                       positive_float, positive_int, print_json)
from erva_ros.core.errors import CLIError

COMMAND = 'map'
HELP = 'road maps from recorded HIL drives: build, info, compare; the road estimate\'s accuracy'
DESCRIPTION = """\
The road at the tyre is estimated from what the ECU measures (an EKF with the road as a
state, smoothed over a recorded drive); drives over one route are fused into a map keyed
by distance along the route (docs/road.md).

  erva map build BAG... --out MAP   smooth each drive's road estimate and add it to MAP
                                    (created if missing; a new drive adds to an existing
                                    map without the old ones)
  erva map info MAP                 route, extent, drives, gaps, variance
  erva map compare MAP --road ...   the map against a known road (simulation)
  erva map accuracy                 the road estimator's error on ISO 8608 A-D and the
                                    paper road, at the shipped sensor noise

BAG is a session bag of a HIL run (erva run --ecu virtual ...): it needs
/erva/ecu/measurements and the distance (/erva/road/estimate, else /erva/road/height).
MAP is an SQLite file.  Bad input (a bag without the HIL topics, another route, a
corrupt or locked map) stops with one line and exit status 2; the map is then unchanged."""


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
    p.add_argument('--out', required=True, metavar='MAP', help='the map file (SQLite)')
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
    return {'build': _build, 'info': _info, 'compare': _compare,
            'accuracy': _accuracy}[args.map_command](args)


# -- build --------------------------------------------------------------------------------
def _build(args) -> int:
    from erva_ros.core.params import load_erva_params
    from erva_ros.core.roadmap import MapError
    from erva_ros.core.roadmap.bag_drive import read_bag_drive
    from erva_ros.core.roadmap.drive import estimate_drive, grid_profile
    from erva_ros.core.roadmap.store import RoadMap

    params = load_erva_params(args.params)
    created = not os.path.exists(args.out)
    road_map = None if created else RoadMap.open(args.out)
    drives = [read_bag_drive(b, warn=bag_warner('erva map build', path=b))
              for b in args.bags]                              # every bag checked first
    digests = set()
    for d in drives:
        if d.record.digest() in digests:
            raise MapError(f'{d.record.source}: given twice')
        digests.add(d.record.digest())
    route = road_map.route if road_map else (args.route or drives[0].record.route)
    for d in drives:
        if d.record.route and route and d.record.route != route:
            raise MapError(f'{d.record.source}: drive on route {d.record.route!r}, the map is '
                           f'of route {route!r}')
    grid = road_map.grid_m if road_map else args.grid
    highpass_m = road_map.highpass_m if road_map else args.highpass
    if road_map is None:
        road_map = RoadMap.create(args.out, route or '', grid, highpass_m)
    results = []
    try:
        with road_map.transaction():
            for d in drives:
                est = estimate_drive(d.record, params, d.ts)
                g = grid_profile(est, grid, highpass_m, ts=d.ts)
                reg = road_map.add_locked(g, d.record.digest(), d.record.source, args.vehicle,
                                          args.search, d.record.speed_mps)
                results.append({'bag': d.record.source, 'cycles': len(d.record.t),
                                'missing_cycles': d.missing_cycles,
                                'repeated_cycles': d.repeated_cycles,
                                'malformed': d.malformed, 'distance_from': d.distance_topic,
                                'offset_m': reg.offset_m, 'scale': reg.scale,
                                'correlation': reg.correlation, 'segments': reg.segments})
    except BaseException:
        road_map.close()
        if created:
            os.remove(args.out)
        raise
    info = _map_info(road_map)
    road_map.close()
    out = {'map': args.out, 'created': created, 'added': results, 'info': info}
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


# -- info ---------------------------------------------------------------------------------
DRIVE_KEYS = ('id', 'source', 'vehicle', 'added_utc', 'offset_m', 'scale', 'correlation',
              'speed_mps')


def _map_info(road_map) -> dict:
    import numpy as np
    p = road_map.profile()
    ok = p.valid
    drives = road_map.drives()
    return {'file': road_map.path, 'route': road_map.route, 'schema_version':
            int(road_map.meta['schema_version']), 'grid_m': p.grid_m, 'highpass_m': p.highpass_m,
            'created_utc': road_map.meta.get('created_utc'), 'drives': len(drives),
            'start_m': p.start_m if p.n else None, 'end_m': p.end_m if p.n else None,
            'nodes': int(ok.sum()), 'gaps_m': [list(g) for g in p.gaps()],
            'drives_per_node': {'min': int(p.drives[ok].min()) if ok.any() else 0,
                                'max': int(p.drives[ok].max()) if ok.any() else 0},
            'height_rms_m': float(np.sqrt(np.mean(p.h[ok] ** 2))) if ok.any() else None,
            'std_mean_m': float(np.sqrt(np.mean(p.var[ok]))) if ok.any() else None,
            'variance_scale': p.variance_scale,
            'drive_list': [{k: d[k] for k in DRIVE_KEYS} for d in drives]}


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
    from erva_ros.core.roads import make_road, RoadError

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
    from erva_ros.core.params import load_erva_params
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
