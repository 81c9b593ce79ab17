"""What a parameter may be: one typed spec family for the CLI, the params files and the nodes.

Each spec knows its allowed values and its meaning, and nothing else (defaults live in
``config/*.yaml``):

* :class:`Number` -- a finite float in ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``), SI unit;
* :class:`Integer` -- a whole number in ``[lo, hi]`` (a YAML ``4.0`` is accepted as 4);
* :class:`Choice` -- one string of a fixed tuple;
* :class:`Flag` -- true or false;
* :class:`Text` -- any string;
* :class:`Texts` -- a list of strings.

A spec with ``live=True`` is a dynamic parameter of the nodes that declare it: it may
change while the node runs (a ROS parameter that is not read-only; docs/live.md), and
takes effect at the node's next sample.  Every other one is read-only while it runs.

``check(key, value, source)`` returns the value converted to its type or raises a
one-line :class:`ParamError` naming the key, the value and what is allowed;
``describe()`` is the allowed range as text; ``argparse()`` gives an option's
``type``/``choices``/``help``.  The same spec serves the command line, the session
params file (``session/run/run_config.py``), the offline loaders and the ROS descriptors
(``ros/parameters.declare``), so the four cannot disagree.
"""

import argparse as _argparse
from dataclasses import dataclass
import difflib
import math
from typing import Any, Dict, Iterable, Optional, Tuple


class ParamError(ValueError):
    """A parameter is missing, of the wrong type, or out of its allowed range."""


def _where(source: str) -> str:
    return f'{source}: ' if source else ''


@dataclass(frozen=True)
class Number:
    """A finite number in ``[lo, hi]`` (``(lo, hi]`` if ``lo_open``), in ``unit``."""

    lo: float
    hi: float
    unit: str
    doc: str
    lo_open: bool = False
    live: bool = False      # may change while the node runs (module doc)

    kind = 'number'
    python_type = float

    def describe(self) -> str:
        """Return the allowed range as text, e.g. ``(0, 10] m/rad``."""
        left = '(' if self.lo_open else '['
        unit = '' if self.unit == '-' else self.unit      # '-': dimensionless
        return f'{left}{self.lo:g}, {self.hi:g}] {unit}'.rstrip()

    def allowed(self) -> str:
        """Return what is allowed and what it means (for --help and descriptors)."""
        return f'{self.kind} in {self.describe()} ({self.doc})'

    def _in_range(self, v: float) -> bool:
        too_low = v <= self.lo if self.lo_open else v < self.lo
        return math.isfinite(v) and not too_low and v <= self.hi

    def _out_of_range(self, key: str, value: Any, source: str) -> ParamError:
        return ParamError(f'{_where(source)}parameter {key!r} = {value!r} is out of range; '
                          f'allowed {self.describe()} ({self.doc})')

    def check(self, key: str, value: Any, source: str = '') -> float:
        """Return ``value`` as float or raise a one-line :class:`ParamError`."""
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ParamError(f'{_where(source)}parameter {key!r} must be a number in '
                             f'{self.describe()}, got {type(value).__name__} {value!r}')
        if not self._in_range(float(value)):
            raise self._out_of_range(key, value, source)
        return float(value)

    def parse(self, text: str):
        """Parse a command-line value (argparse ``type``): the value or ArgumentTypeError."""
        try:
            return self.check('', self.python_type(text))
        except (ValueError, ParamError):
            article = 'an' if self.kind[0] in 'aeiou' else 'a'
            raise _argparse.ArgumentTypeError(
                f'{text!r} is not {article} {self.kind} in {self.describe()}') from None

    def argparse(self, help: str = '', checked: bool = True) -> Dict[str, Any]:
        """Return ``add_argument`` keywords: ``type`` and ``help`` (``help`` or the doc).

        ``checked=False`` only converts the text (int or float): for an option whose value
        is checked later with :meth:`check`, whose one-line error names the parameter.
        """
        kind = self.parse if checked else self.python_type
        return {'type': kind, 'help': f'{help or self.doc}; {self.describe()}'}


@dataclass(frozen=True)
class Integer(Number):
    """A whole number in ``[lo, hi]``; a float that is a whole number (YAML ``4.0``) is one."""

    kind = 'integer'
    python_type = int

    def check(self, key: str, value: Any, source: str = '') -> int:
        """Return ``value`` as int or raise a one-line :class:`ParamError`."""
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ParamError(f'{_where(source)}parameter {key!r} must be an integer in '
                             f'{self.describe()} ({self.doc}), got '
                             f'{type(value).__name__} {value!r}')
        if not self._in_range(float(value)):
            raise self._out_of_range(key, value, source)
        return int(value)


@dataclass(frozen=True)
class Choice:
    """One string of ``options``."""

    options: Tuple[str, ...]
    doc: str
    live: bool = False

    kind = 'choice'

    def describe(self) -> str:
        """Return the allowed values as text."""
        return f'one of {", ".join(self.options)}'

    def allowed(self) -> str:
        """Return what is allowed and what it means."""
        return f'{self.describe()} ({self.doc})'

    def check(self, key: str, value: Any, source: str = '') -> str:
        """Return ``value`` if it is one of the options, else a one-line ParamError."""
        if not isinstance(value, str) or value not in self.options:
            raise ParamError(f'{_where(source)}parameter {key!r} = {value!r} is not allowed; '
                             f'choose one of {", ".join(self.options)} ({self.doc})')
        return value

    def argparse(self, help: str = '') -> Dict[str, Any]:
        """Return ``add_argument`` keywords: ``choices`` and ``help``."""
        return {'choices': self.options, 'help': help or self.doc}


@dataclass(frozen=True)
class Flag:
    """True or false."""

    doc: str
    live: bool = False

    kind = 'flag'

    def describe(self) -> str:
        """Return the allowed values as text."""
        return 'true or false'

    def allowed(self) -> str:
        """Return what is allowed and what it means."""
        return f'{self.describe()} ({self.doc})'

    def check(self, key: str, value: Any, source: str = '') -> bool:
        """Return ``value`` if it is a bool, else a one-line ParamError."""
        if not isinstance(value, bool):
            raise ParamError(f'{_where(source)}parameter {key!r} must be true or false '
                             f'({self.doc}), got {value!r}')
        return value

    def argparse(self, help: str = '') -> Dict[str, Any]:
        """Return ``add_argument`` keywords of an on/off switch."""
        return {'action': 'store_true', 'help': help or self.doc}


@dataclass(frozen=True)
class Text:
    """Any string."""

    doc: str
    live = False

    kind = 'string'

    def describe(self) -> str:
        """Return the allowed values as text."""
        return 'a string'

    def allowed(self) -> str:
        """Return what is allowed and what it means."""
        return self.doc

    def check(self, key: str, value: Any, source: str = '') -> str:
        """Return ``value`` if it is a string, else a one-line ParamError."""
        if not isinstance(value, str):
            raise ParamError(f'{_where(source)}parameter {key!r} must be a string '
                             f'({self.doc}), got {value!r}')
        return value

    def argparse(self, help: str = '') -> Dict[str, Any]:
        """Return ``add_argument`` keywords: ``help``."""
        return {'help': help or self.doc}


@dataclass(frozen=True)
class Texts:
    """A list of strings."""

    doc: str
    live = False

    kind = 'list of strings'

    def describe(self) -> str:
        """Return the allowed values as text."""
        return 'a list of strings'

    def allowed(self) -> str:
        """Return what is allowed and what it means."""
        return self.doc

    def check(self, key: str, value: Any, source: str = '') -> list:
        """Return ``value`` as a list if it is a list of strings, else a one-line ParamError."""
        if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
            raise ParamError(f'{_where(source)}parameter {key!r} must be a list of strings '
                             f'({self.doc}), got {value!r}')
        return list(value)


def closest_key(key: str, known: Iterable[str]) -> Optional[str]:
    """Return the known key most like ``key`` (a typo, another case), or None."""
    by_lower = {k.lower(): k for k in sorted(known, reverse=True)}
    close = difflib.get_close_matches(key.lower(), list(by_lower), n=1, cutoff=0.6)
    return by_lower[close[0]] if close else None


def unknown_parameters(unknown: Iterable[str], known: Iterable[str], source: str = '',
                       what: str = 'parameter(s)') -> ParamError:
    """Return the one-line ParamError of keys no table knows, with the closest known ones.

    ``unknown parameter(s) speeed_mps; did you mean 'speed_mps'?`` (several: each with
    its own); where nothing is close, the known keys are listed instead.
    """
    unknown, known = sorted(map(str, unknown)), sorted(set(map(str, known)))
    close = {key: closest_key(key, known) for key in unknown}
    found = {k: c for k, c in close.items() if c}
    if len(unknown) == 1 and found:
        hint = f'; did you mean {found[unknown[0]]!r}?'
    elif found:
        hint = '; did you mean ' + ', '.join(f'{c!r} for {k!r}' for k, c in found.items()) + '?'
    else:
        hint = f'; known: {", ".join(known)}'
    return ParamError(f'{_where(source)}unknown {what} {", ".join(unknown)}{hint}')


def check_all(specs: Dict[str, Any], values: Dict[str, Any], source: str = '',
              defaults: Dict[str, Any] = None) -> Dict[str, Any]:
    """Return ``values`` (over ``defaults``) checked by ``specs``; unknown keys: ParamError."""
    out = dict(defaults or {})
    out.update(values)
    unknown = sorted(set(out) - set(specs))
    if unknown:
        raise unknown_parameters(unknown, specs, source)
    return {key: specs[key].check(key, value, source) for key, value in out.items()}


__all__ = ['ParamError', 'Number', 'Integer', 'Choice', 'Flag', 'Text', 'Texts', 'closest_key',
           'unknown_parameters', 'check_all']
