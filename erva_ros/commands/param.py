"""``erva param``: a running node's parameters, as ``ros2 param`` (list, get, set, describe...)."""

from erva_ros.commands._common import add_json_option, positive_float, print_json
from erva_ros.core.errors import CLIError

COMMAND = 'param'
HELP = 'a running node\'s parameters, as ros2 param: list, get, set (live ones), describe, dump'
DESCRIPTION = """\
The verbs of ros2 param, over the nodes' own rcl_interfaces services (no ros2 CLI
needed); NODE is a fully qualified node name, e.g. /erva/nmpc_node:

  erva param list [NODE]            the parameters of NODE (of every node: without NODE)
  erva param get NODE NAME          a value
  erva param set NODE NAME VALUE    change a live parameter: it takes effect at the
                                    node's next sample and is announced on
                                    /parameter_events; a bad value or a read-only
                                    parameter is refused with the reason (exit 1)
  erva param describe NODE NAME...  type, meaning, range, read-only and why
  erva param dump NODE              all values as a ROS 2 params file (YAML)

VALUE is read as the parameter's declared type (0 sets a double to 0.0).  Several
NAME VALUE pairs after `set` change them at once (one request, all or none), e.g.
`erva param set /erva/nmpc_node u_min 2000 u_max 15000`.

The live parameters of nmpc_node: alpha1, alpha2, u_min, u_max, use_preview,
road_prediction, fallback, time_budget_s, state_timeout_periods (docs/live.md: which,
and why the others are read-only).

Examples:
  erva param set /erva/nmpc_node alpha1 0.5
  erva param get /erva/nmpc_node alpha1
  erva param describe /erva/nmpc_node horizon u_max"""


def add_arguments(parser):
    sub = parser.add_subparsers(dest='param_command', metavar='VERB')
    sub.required = True

    def verb(name, help_text, node_required=True):
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.add_argument('node', metavar='NODE', nargs=None if node_required else '?',
                       default=None, help='fully qualified node name, e.g. /erva/nmpc_node')
        p.add_argument('--timeout', type=positive_float, default=5.0, metavar='S',
                       help='wait at most S s for the node to answer (default 5)')
        add_json_option(p)
        return p

    verb('list', 'list the parameters of NODE (of every node with parameter services '
                 'without NODE)', node_required=False)
    p = verb('get', 'print the value of a parameter')
    p.add_argument('name', metavar='NAME')
    p = verb('set', 'set parameters (NAME VALUE [NAME VALUE ...], all at once)')
    p.add_argument('assignments', metavar='NAME VALUE', nargs='+')
    p = verb('describe', 'print the descriptor of parameters: type, meaning, range, '
                         'read-only and why')
    p.add_argument('names', metavar='NAME', nargs='+')
    verb('dump', 'print every parameter of NODE as a ROS 2 params file (YAML)')


def _node(name: str) -> str:
    if not name.startswith('/') or name.endswith('/') or '//' in name:
        raise CLIError(f'NODE {name!r}: give the fully qualified name, e.g. /erva/nmpc_node')
    return name


def _value_line(value) -> str:
    """Return ros2 param get's line for a value."""
    kind = {bool: 'Boolean', int: 'Integer', float: 'Double', str: 'String'}.get(type(value))
    if value is None:
        return 'Parameter not set.'
    if kind is None:
        return f'{"String" if all(isinstance(v, str) for v in value) else "Array"} values ' \
               f'are: {list(value)}'
    return f'{kind} value is: {value}'


def _describe_lines(d) -> list:
    out = [f'Parameter name: {d.name}', f'  Type: {d.type}',
           f'  Description: {d.description}']
    if d.constraints or d.range or d.read_only:
        out.append('  Constraints:')
        if d.range:
            out += [f'    Min value: {d.range[0]}', f'    Max value: {d.range[1]}']
            if d.range[2]:
                out.append(f'    Step: {d.range[2]}')
        if d.read_only:
            out.append('    Read only: true')
        if d.constraints:
            out.append(f'    Additional constraints: {d.constraints}')
    return out


def main(args) -> int:
    from erva_ros.ros.param_client import ParameterTool
    node = _node(args.node) if args.node else None
    assignments = {}
    if args.param_command == 'set':
        pairs = args.assignments
        if len(pairs) % 2:
            raise CLIError(f'set: give NAME VALUE pairs; {pairs[-1]!r} has no value')
        assignments = dict(zip(pairs[0::2], pairs[1::2]))
    tool = ParameterTool(args.timeout)
    try:
        return _run(tool, args, node, assignments)
    finally:
        tool.close()


def _run(tool, args, node, assignments) -> int:
    verb = args.param_command
    if verb == 'list':
        nodes = [node] if node else tool.nodes()
        listed = {n: tool.list(n) for n in nodes}
        if args.json:
            print_json(listed)
        for n, names in listed.items():
            if not args.json:
                print(f'{n}:')
                print('\n'.join(f'  {name}' for name in names))
        return 0
    if verb == 'get':
        if args.name not in tool.list(node):
            raise CLIError(f'node {node} has no parameter {args.name!r}')
        value = tool.get(node, [args.name])[args.name]
        print_json({args.name: value}) if args.json else print(_value_line(value))
        return 0
    if verb == 'describe':
        known = tool.list(node)
        missing = [n for n in args.names if n not in known]
        if missing:
            raise CLIError(f'node {node} has no parameter {missing[0]!r}')
        described = tool.describe(node, args.names)
        if args.json:
            print_json([d.__dict__ for d in described])
        else:
            print('\n'.join(line for d in described for line in _describe_lines(d)))
        return 0
    if verb == 'dump':
        values = tool.get(node, tool.list(node))
        if args.json:
            print_json(values)
        else:
            import yaml
            name = node.rsplit('/', 1)[1]
            ns = node.rsplit('/', 1)[0] or '/'
            print(yaml.safe_dump({f'{ns.rstrip("/")}/{name}': {'ros__parameters': values}},
                                 sort_keys=False), end='')
        return 0
    reason = tool.set(node, assignments)      # verb == 'set'
    if args.json:
        print_json({'node': node, 'set': assignments, 'successful': reason is None,
                    'reason': reason or ''})
    elif reason is None:
        print('Set parameter successful')
    else:
        print(f'Setting parameter failed: {reason}')
    return 0 if reason is None else 1
