"""Declare a node's parameters from its schema, with descriptors, through rclpy's public API.

Each node's parameters are :data:`erva_ros.core.node_params.SCHEMAS` ``[node]``: their
specs (:mod:`erva_ros.core.specs`) and their defaults (the shipped ``config/*.yaml``).
:func:`declare_schema` declares every one read-only with a ParameterDescriptor
(description, FloatingPointRange or IntegerRange, allowed values as
additional_constraints), so ``ros2 param describe`` shows the range.

Values come from rclpy's own ``--ros-args --params-file F -p name:=value`` handling.
A parameter is first declared with dynamic typing, so rclpy applies any override; the
value is then checked by the spec -- the same check the offline tools and the session
file use -- so a bad value stops the node with one
:class:`~erva_ros.core.params.ParamError` line naming the key, the value and the range;
only then does the parameter get its typed, read-only descriptor
(``Node.set_descriptor``).  A whole number given for a floating-point parameter
(``alpha2: 1``) is accepted.
"""

from typing import Any, Dict

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType)
from rclpy.parameter import Parameter

from erva_ros.core.node_params import NodeSchema, SCHEMAS
from erva_ros.core.specs import Choice, Flag, Integer, Number, Texts

_TYPES = {Integer: ParameterType.PARAMETER_INTEGER, Number: ParameterType.PARAMETER_DOUBLE,
          Flag: ParameterType.PARAMETER_BOOL, Texts: ParameterType.PARAMETER_STRING_ARRAY}


def descriptor(name: str, spec) -> ParameterDescriptor:
    """Return the read-only ParameterDescriptor of a spec (what ``ros2 param describe`` shows)."""
    desc = ParameterDescriptor(name=name, read_only=True,
                               type=_TYPES.get(type(spec), ParameterType.PARAMETER_STRING))
    if isinstance(spec, Number):
        desc.description = f'{spec.doc} ({spec.unit})'
        desc.additional_constraints = spec.describe()
        if isinstance(spec, Integer):
            desc.integer_range = [IntegerRange(from_value=int(spec.lo), to_value=int(spec.hi),
                                               step=1)]
        else:
            desc.floating_point_range = [FloatingPointRange(
                from_value=float(spec.lo), to_value=float(spec.hi), step=0.0)]
    elif isinstance(spec, Choice):
        desc.description = spec.doc
        desc.additional_constraints = spec.describe()
    else:
        desc.description = spec.doc
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


__all__ = ['descriptor', 'declare', 'declare_schema', 'declare_node_parameters']
