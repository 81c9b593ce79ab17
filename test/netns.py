"""Two Linux network namespaces joined by a veth pair: two "hosts" on one machine.

Test support for the loop split across hosts (docs/hil.md).  :class:`HostPair` creates
namespaces ``<prefix>a`` and ``<prefix>b`` with their loopback up and a veth pair
``<prefix>a``/``<prefix>b`` carrying private addresses that exist inside the namespaces
only (IPv6 off on the veth, so the kernel sends no neighbour discovery of its own).
Nothing in them can reach a real interface.  Names are unique per pytest process and
pair; :meth:`HostPair.close` (also on failure, as a context manager) kills what still
runs inside and deletes both namespaces, which removes the veth pair.

Counters come from inside each namespace: the veth's packets/bytes (sysfs) and the
namespace's multicast / broadcast IP counters (/proc/net/netstat ``IpExt``).
"""

import itertools
import os
import re
import shutil
import signal
import subprocess
import time
from typing import Dict, List, Optional

_pairs = itertools.count()
NETSTAT_KEYS = ('OutMcastPkts', 'InMcastPkts', 'OutBcastPkts', 'InBcastPkts')


def _ip(*args, netns: Optional[str] = None, check: bool = True) -> subprocess.CompletedProcess:
    argv = [*(['ip', 'netns', 'exec', netns] if netns else []), 'ip', *args]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=30)
    if check and proc.returncode != 0:
        raise RuntimeError(f'{" ".join(argv)}: {proc.stderr.strip()}')
    return proc


def unavailable() -> Optional[str]:
    """Return why namespaces cannot be made here (one line), or None if they can."""
    if shutil.which('ip') is None:
        return 'the ip command (iproute2) is not installed'
    probe = f'erva_probe_{os.getpid()}'
    made = _ip('netns', 'add', probe, check=False)
    if made.returncode != 0:
        why = (made.stderr.strip().splitlines() or ['not permitted'])[0]
        return f'cannot create network namespaces: {why}'
    _ip('netns', 'del', probe, check=False)
    return None


def remove_orphans() -> None:
    """Delete the namespaces of test processes that died without cleaning up (SIGKILL)."""
    for name in _ip('netns', 'list', check=False).stdout.split():
        m = re.fullmatch(r'ev(\d+)x\d+[ab]', name)
        if m and not os.path.exists(f'/proc/{m.group(1)}'):
            _ip('netns', 'del', name, check=False)


class HostPair:
    """Namespaces ``a`` and ``b`` with a veth link ``subnet.1`` <-> ``subnet.2`` (/30)."""

    def __init__(self, subnet: str = '10.203.0'):
        remove_orphans()
        n = next(_pairs)
        self.prefix = f'ev{os.getpid() % 100000}x{n}'          # veth names <= 15 chars
        self.ns = {'a': f'{self.prefix}a', 'b': f'{self.prefix}b'}
        self.veth = dict(self.ns)                              # each end named as its ns
        self.addr = {'a': f'{subnet}.1', 'b': f'{subnet}.2'}
        self._made: List[str] = []
        try:
            for side in 'ab':
                _ip('netns', 'add', self.ns[side])
                self._made.append(self.ns[side])
            _ip('link', 'add', self.veth['a'], 'netns', self.ns['a'], 'type', 'veth',
                'peer', 'name', self.veth['b'], 'netns', self.ns['b'])
            for side in 'ab':
                ns, dev = self.ns[side], self.veth[side]
                _ip('link', 'set', 'lo', 'up', netns=ns)
                with open(os.devnull, 'w') as null:
                    subprocess.run(['ip', 'netns', 'exec', ns, 'sysctl', '-q', '-w',
                                    f'net.ipv6.conf.{dev}.disable_ipv6=1'], stdout=null,
                                   stderr=null, timeout=30)
                _ip('addr', 'add', f'{self.addr[side]}/30', 'dev', dev, netns=ns)
                _ip('link', 'set', dev, 'up', netns=ns)
            self._wait_running()
        except BaseException:
            self.close()
            raise

    def _wait_running(self, timeout: float = 30.0) -> None:
        """Return once both veth ends are running (carrier), as a cabled host's NIC is.

        The kernel reports the carrier a moment after ``link set up``.  A Fast DDS
        process started before that finds no running interface, and its host id falls
        back to one value on both sides: each side would then take the other for itself
        and use shared memory instead of the link: nothing connects (as when the link
        comes up 4 s after the loop started).
        """
        end = time.monotonic() + timeout
        while True:
            states = {side: _ip('netns', 'exec', self.ns[side], 'cat',
                                f'/sys/class/net/{self.veth[side]}/operstate').stdout.strip()
                      for side in 'ab'}
            # The kernel's IFF_RUNNING, which Fast DDS reads, is operstate up or unknown.
            if all(state in ('up', 'unknown') for state in states.values()):
                return
            if time.monotonic() > end:
                raise RuntimeError(f'veth pair not running after {timeout:.0f} s: {states}')
            time.sleep(0.02)

    def __enter__(self) -> 'HostPair':
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def exec_prefix(self, side: str) -> List[str]:
        """Return the argv prefix that runs a command on host ``side``."""
        return ['ip', 'netns', 'exec', self.ns[side]]

    def link(self, side: str, up: bool) -> None:
        """Take host ``side``'s end of the link down or up (as a cable pulled)."""
        _ip('link', 'set', self.veth[side], 'up' if up else 'down', netns=self.ns[side])

    def counters(self, side: str) -> Dict[str, int]:
        """Return the veth's rx/tx packets and bytes and the namespace's IpExt counters."""
        ns, dev = self.ns[side], self.veth[side]
        out = {}
        for key in ('rx_packets', 'tx_packets', 'rx_bytes', 'tx_bytes'):
            text = _ip('netns', 'exec', ns, 'cat', f'/sys/class/net/{dev}/statistics/{key}')
            out[key] = int(text.stdout)
        netstat = _ip('netns', 'exec', ns, 'cat', '/proc/net/netstat').stdout
        lines = [ln.split() for ln in netstat.splitlines() if ln.startswith('IpExt:')]
        stats = dict(zip(lines[0][1:], (int(v) for v in lines[1][1:])))
        out.update({k: stats[k] for k in NETSTAT_KEYS})
        return out

    def close(self) -> None:
        """Kill what still runs inside, delete the namespaces (and with them the veth)."""
        for ns in self._made:
            pids = _ip('netns', 'pids', ns, check=False).stdout.split()
            for pid in pids:
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
            end = time.monotonic() + 5.0
            while pids and time.monotonic() < end:
                pids = _ip('netns', 'pids', ns, check=False).stdout.split()
                time.sleep(0.05)
            _ip('netns', 'del', ns, check=False)
        self._made = []

    def exists(self) -> bool:
        """Return True while any of the two namespaces exists."""
        listed = _ip('netns', 'list', check=False).stdout.split()
        return any(ns in listed for ns in self.ns.values())
