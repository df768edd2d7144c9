"""Is there an IPv4 route to libcamera's software-sync multicast group?

libcamera's Raspberry Pi sync algorithm (``src/ipa/rpi/controller/rpi/sync.cpp``) talks over
UDP multicast to ``239.255.255.250`` port 10000 (``Sync::read``: ``kDefaultGroup``,
``kDefaultPort``).  The client joins the group with ``IP_ADD_MEMBERSHIP`` on ``INADDR_ANY``,
which the kernel resolves through the routing table: with no route to the group (a box with
neither Wi-Fi nor Ethernet up) the join fails with ENODEV, ``Sync::initialiseSocket`` closes the
socket and the client never reports ``SyncReady``; the server's ``sendto`` fails with
ENETUNREACH.  A host route through the loopback interface is enough for two cameras on one
box::

    ip route add 239.255.255.250/32 dev lo

The check reads the kernel's main IPv4 routing table as ``/proc/net/route`` shows it, through
an injectable reader, so tests never look at the machine's real network.  Routes in other
policy-routing tables are not seen (a box that routes multicast through one is told there is
no route).
"""

from __future__ import annotations

import socket
import sys
from dataclasses import dataclass
from typing import Callable

SYNC_GROUP = "239.255.255.250"          # sync.cpp Sync::read kDefaultGroup
PROC_NET_ROUTE = "/proc/net/route"
RTF_UP, RTF_REJECT = 0x0001, 0x0200     # linux/route.h
ROUTE_COMMAND = f"ip route add {SYNC_GROUP}/32 dev lo"


@dataclass(frozen=True)
class Route:
    """One line of /proc/net/route (addresses as big-endian integers)."""

    iface: str
    destination: int
    mask: int
    flags: int
    metric: int


def _address(field: str) -> int:
    # /proc/net/route prints the address as the hex of the in-memory (network order) word
    return int.from_bytes(int(field, 16).to_bytes(4, sys.byteorder), "big")


def parse_proc_net_route(text: str) -> list[Route]:
    """The routes of a /proc/net/route text; the header and malformed lines are skipped."""
    routes = []
    for line in text.splitlines()[1:]:
        cols = line.split()
        if len(cols) < 8:
            continue
        try:
            routes.append(Route(iface=cols[0], destination=_address(cols[1]), mask=_address(cols[7]),
                                flags=int(cols[3], 16), metric=int(cols[6])))
        except ValueError:
            continue
    return routes


def route_to(group: str, routes: list[Route]) -> Route | None:
    """The route the kernel's main table would pick for ``group`` (longest prefix, lowest metric)."""
    addr = int.from_bytes(socket.inet_aton(group), "big")
    usable = [r for r in routes
              if r.flags & RTF_UP and not r.flags & RTF_REJECT and addr & r.mask == r.destination & r.mask]
    if not usable:
        return None
    return max(usable, key=lambda r: (bin(r.mask).count("1"), -r.metric))


def read_proc_net_route(path: str = PROC_NET_ROUTE) -> str:
    with open(path, encoding="ascii", errors="replace") as f:
        return f.read()


def multicast_route(group: str = SYNC_GROUP, reader: Callable[[], str] = read_proc_net_route) -> str | None:
    """The interface the route to ``group`` goes through, or None when there is none.

    Raises OSError when the routing table cannot be read (the caller decides what that means).
    """
    route = route_to(group, parse_proc_net_route(reader()))
    return None if route is None else route.iface
