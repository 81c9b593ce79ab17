"""Declare a node's parameters from its schema, with descriptors, through rclpy's public API.

Each node's parameters are :data:`erva_ros.core.settings.schemas.SCHEMAS` ``[node]``: their
specs (:mod:`erva_ros.core.settings.specs`) and their defaults (the shipped ``config/*.yaml``).
:func:`declare_schema` declares every one with a ParameterDescriptor (description,
FloatingPointRange or IntegerRange, allowed values as additional_constraints), so
``ros2 param describe`` shows the range.  A parameter whose spec is ``live`` is dynamic
(``read_only`` false: ``ros2 param set`` changes it while the node runs, checked by the
node's callback, :func:`on_set_callback`); every other one is read-only, and its
description says why (:func:`erva_ros.core.settings.schemas.read_only_reason`).

Values come from rclpy's own ``--ros-args --params-file F -p name:=value`` handling.
A parameter is first declared with dynamic typing, so rclpy applies any override; the
value is then checked by the spec -- the same check the offline tools and the session
file use -- so a bad value stops the node with one
:class:`~erva_ros.core.model.params.ParamError` line naming the key, the value and the range;
only then does the parameter get its typed, read-only descriptor
(``Node.set_descriptor``).  A whole number given for a floating-point parameter
(``alpha2: 1``) is accepted.
"""

from typing import Any, Callable, Dict, List, Mapping

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rclpy.parameter import Parameter

from erva_ros.core.settings.schemas import NodeSchema, read_only_reason, SCHEMAS
from erva_ros.core.model.params import ParamError
from erva_ros.core.settings.specs import Choice, Flag, Integer, Number, Texts

#: What a live parameter's description ends with.
LIVE_NOTE = 'live: may change while the node runs, takes effect at its next sample'
#: What a read-only parameter's description says before its reason.
READ_ONLY_NOTE = 'read-only while the node runs'

_TYPES = {Integer: ParameterType.PARAMETER_INTEGER, Number: ParameterType.PARAMETER_DOUBLE,
          Flag: ParameterType.PARAMETER_BOOL, Texts: ParameterType.PARAMETER_STRING_ARRAY}


def descriptor(name: str, spec) -> ParameterDescriptor:
    """Return the ParameterDescriptor of a spec (what ``ros2 param describe`` shows).

    Read-only unless the spec is ``live``; the description ends with which, and why.
    """
    desc = ParameterDescriptor(name=name, read_only=not spec.live,
                               type=_TYPES.get(type(spec), ParameterType.PARAMETER_STRING))
    note = LIVE_NOTE if spec.live else f'{READ_ONLY_NOTE}: {read_only_reason(name)}'
    if isinstance(spec, Number):
        desc.description = f'{spec.doc} ({spec.unit}); {note}'
        desc.additional_constraints = spec.describe()
        if isinstance(spec, Integer):
            desc.integer_range = [IntegerRange(from_value=int(spec.lo), to_value=int(spec.hi),
                                               step=1)]
        else:
            desc.floating_point_range = [FloatingPointRange(
                from_value=float(spec.lo), to_value=float(spec.hi), step=0.0)]
    elif isinstance(spec, Choice):
        desc.description = f'{spec.doc}; {note}'
        desc.additional_constraints = spec.describe()
    else:
        desc.description = f'{spec.doc}; {note}'
    return desc


def declare(node, name: str, spec, default: Any) -> Any:
    """Declare parameter ``name`` (its override, else ``default``); return the checked value."""
    given = node.declare_parameter(
        name, default, ParameterDescriptor(name=name, dynamic_typing=True)).value
    value = spec.check(name, given)
    typed = Parameter(name, value=value).get_parameter_value()
    node.set_descriptor(name, descriptor(name, spec), alternative_value=typed)
    return value


def declare_schema(node, schema: NodeSchema) -> Dict[str, Any]:
    """Declare every parameter of ``schema``; return {name: checked value}."""
    defaults = schema.defaults()
    return {name: declare(node, name, spec, defaults[name]) for name, spec, _ in schema.items()}


def declare_node_parameters(node, name: str) -> Dict[str, Any]:
    """Declare the parameters of node ``name`` (:data:`SCHEMAS`); return their values."""
    return declare_schema(node, SCHEMAS[name])


def on_set_callback(schema: NodeSchema, check: Callable[[Mapping[str, Any]], None]
                    ) -> Callable[[List[Parameter]], SetParametersResult]:
    """Return an ``add_on_set_parameters_callback`` callback for the live parameters.

    rclpy has refused read-only parameters, wrong types and values outside a
    descriptor's range before it calls this.  Each value is checked by its spec, then
    all together by ``check({name: value})`` (the node's: it stages them for its next
    sample, or raises :class:`ParamError`); a refusal comes back as the result's
    ``reason``, one line naming the key, the value and the rule, and nothing changes
    (rclpy sets nothing, the node staged nothing).
    """
    specs = schema.specs()

    def callback(parameters: List[Parameter]) -> SetParametersResult:
        try:
            values = {}
            for p in parameters:
                spec = specs.get(p.name)
                if spec is None or not spec.live:     # (rclpy refused these already)
                    raise ParamError(f'parameter {p.name!r} is {READ_ONLY_NOTE}: '
                                     f'{read_only_reason(p.name)}')
                values[p.name] = spec.check(p.name, p.value)
            check(values)
        except ParamError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)
    return callback


__all__ = ['LIVE_NOTE', 'READ_ONLY_NOTE', 'descriptor', 'declare', 'declare_schema',
           'declare_node_parameters', 'on_set_callback']
