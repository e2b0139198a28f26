"""Budgets per remote address that outlive the address's connections.

A budget kept per connection, or dropped with an address's last connection, resets
whenever the client reconnects: a loop of connect, three calibrations, drop got ~370
calibrations a second through a limit of 4 (issue 27). Here an address's budget stays
until its window has passed since it was last refilled (it is full again then, the same
as a fresh one), and the table holds at most ``max_addresses`` of them, the least
recently used going first, so that no number of addresses grows it without bound.

An IPv6 client is counted by its /64: one host gets a whole /64, and a budget per
address would give it 2**64 of them.
"""

from __future__ import annotations

import ipaddress
from collections import OrderedDict

from posecast.server.limits import Budget

# one entry is a Budget and a key: ~200 B, so the table stays under ~13 MB
MAX_ADDRESSES = 65536
IPV6_PREFIX = 64


def address_key(remote_address: object) -> str:
    """What a client's per-address limits count by: its IPv4 address, or its IPv6
    /64 ("2001:db8:1:2::/64"); "?" for a transport without a peer address."""
    if not isinstance(remote_address, tuple) or not remote_address:
        return "?"
    host = str(remote_address[0])
    if ":" not in host:  # IPv4: as it is (ip_address costs ~40 us, on every upgrade)
        return host
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        return host
    if isinstance(ip, ipaddress.IPv6Address):
        if ip.ipv4_mapped is not None:  # ::ffff:a.b.c.d is an IPv4 client
            return str(ip.ipv4_mapped)
        return str(ipaddress.IPv6Network((ip, IPV6_PREFIX), strict=False))
    return host


def forwarded_client(header_values: list[str]) -> str | None:
    """The client's address as a trusted reverse proxy reports it: the last entry of
    X-Forwarded-For, the one the proxy added itself (those before it came from the
    client and prove nothing). None when it is missing or not an IP address."""
    entries = ",".join(header_values).split(",")
    last = entries[-1].strip()
    try:
        return str(ipaddress.ip_address(last))
    except ValueError:
        return None


def normalized_ip(text: str) -> str:
    """``text`` as the canonical form of its IP address (ValueError if it is none)."""
    return str(ipaddress.ip_address(text.strip()))


class AddressBudgets:
    """One ``Budget(per_s, burst)`` per address key, kept across connections."""

    def __init__(self, per_s: float, burst: int, max_addresses: int = MAX_ADDRESSES
                 ) -> None:
        self.per_s = per_s
        self.burst = burst
        self.max_addresses = max_addresses
        self._budgets: OrderedDict[str, Budget] = OrderedDict()  # least recent first

    def __len__(self) -> int:
        return len(self._budgets)

    def take(self, key: str, t: float, n: int = 1) -> bool:
        """Spend ``n`` from ``key``'s budget at time ``t``; False (nothing spent) when
        it has fewer left."""
        return self.get(key, t).take(t, n)

    def get(self, key: str, t: float) -> Budget:
        """``key``'s budget (made full if it had none), as the most recently used."""
        self._forget_refilled(t)
        budget = self._budgets.get(key)
        if budget is None:
            budget = self._budgets[key] = Budget(self.per_s, self.burst)
            while len(self._budgets) > self.max_addresses:
                self._budgets.popitem(last=False)
        else:
            self._budgets.move_to_end(key)
        return budget

    def peek(self, key: str) -> Budget | None:
        """``key``'s budget if it has one; nothing changes."""
        return self._budgets.get(key)

    def _forget_refilled(self, t: float) -> None:
        """Drop the least recently used budgets whose window has passed: they would be
        full at their next use anyway."""
        budgets = self._budgets
        while budgets:
            key, oldest = next(iter(budgets.items()))
            if t < oldest.refill_at:
                return
            del budgets[key]
