"""Input QoS that matches the graph: which reliability each input subscription uses (no rclpy).

`qos_reliability` 'auto' (per topic: `topics.<key>.qos_reliability`) picks what
`ros2 topic echo` picks: best effort when any publisher found on the topic is best effort
(a reliable subscription does not match it), else reliable (nothing lost in transport).
The node re-checks as publishers come and go and re-creates the subscription when the
choice changes; with no publisher it keeps what it has. 'reliable' and 'best_effort' are
fixed. A publisher whose QoS the subscription cannot match is counted and described
("publisher best_effort, subscription reliable"), never taken for a missing publisher.

Publisher infos are duck-typed: `.qos_profile.reliability` / `.durability` with a `.name`
(rclpy's TopicEndpointInfo).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
import threading
from typing import Any

RELIABLE, BEST_EFFORT, AUTO = 'reliable', 'best_effort', 'auto'


def policy_name(policy: Any) -> str:
    """ReliabilityPolicy.BEST_EFFORT -> 'best_effort' (any enum with a .name, or a string)."""
    return str(getattr(policy, 'name', policy)).lower()


def choose_reliability(setting: str, publishers: Sequence[Any], current: str | None) -> str:
    """The reliability an input subscription should use now: 'reliable' or 'best_effort'.

    setting: 'auto', 'reliable' or 'best_effort'; publishers: the topic's publisher infos;
    current: what the subscription uses now (None: none yet). 'auto' without publishers
    keeps `current` (reliable at first), so a publisher leaving does not re-create it.
    """
    if setting != AUTO:
        return setting
    kinds = {policy_name(p.qos_profile.reliability) for p in publishers}
    if BEST_EFFORT in kinds:
        return BEST_EFFORT
    if kinds:
        return RELIABLE
    return current or RELIABLE


def incompatible(publishers: Sequence[Any], reliability: str) -> list[str]:
    """One description per publisher the subscription cannot match (reliability, durability).

    The subscription is volatile, so only a best-effort publisher against a reliable
    subscription is incompatible: 'publisher best_effort, subscription reliable'.
    """
    out = []
    for p in publishers:
        offered = policy_name(p.qos_profile.reliability)
        if reliability == RELIABLE and offered == BEST_EFFORT:
            out.append(f'publisher {offered}, subscription {reliability}')
    return out


@dataclass
class TopicQoS:
    """One input topic's QoS state (see InputQoS)."""

    setting: str                         # auto / reliable / best_effort (parameter)
    reliability: str = RELIABLE          # what the subscription uses now
    publishers: int = 0                  # on the graph, matched or not
    incompatible: list[str] = field(default_factory=list)   # per incompatible publisher
    events: int = 0                      # incompatible-QoS events from the middleware
    resubscribed: int = 0                # subscriptions re-created to follow the publishers
    logged: set[str] = field(default_factory=set)            # descriptions already warned


class InputQoS:
    """The input topics' QoS: choices, incompatibility counts and descriptions (thread-safe)."""

    def __init__(self, settings: Sequence[str]) -> None:
        self._lock = threading.Lock()
        self.topics = [TopicQoS(s) for s in settings]

    def choose(self, index: int, publishers: Sequence[Any]) -> str | None:
        """The reliability topic `index` should switch to, or None to keep its subscription."""
        with self._lock:
            t = self.topics[index]
            wanted = choose_reliability(t.setting, publishers, t.reliability)
            return None if wanted == t.reliability else wanted

    def subscribed(self, index: int, reliability: str, again: bool = False) -> None:
        """Topic `index` is (re-)subscribed with `reliability`."""
        with self._lock:
            t = self.topics[index]
            t.reliability = reliability
            t.resubscribed += again

    def observe(self, index: int, publishers: Sequence[Any]) -> list[str]:
        """Record the topic's publishers; returns the incompatibilities not yet warned about."""
        with self._lock:
            t = self.topics[index]
            t.publishers = len(publishers)
            t.incompatible = incompatible(publishers, t.reliability)
            new = sorted(set(t.incompatible) - t.logged)
            t.logged.update(new)
            return new

    def on_event(self, index: int, count_change: int) -> None:
        """An incompatible-QoS event of topic `index`'s subscription (middleware)."""
        with self._lock:
            self.topics[index].events += max(int(count_change), 1)

    def problem(self, index: int) -> str:
        """'' or why topic `index` hears nothing from some publisher (for /diagnostics)."""
        with self._lock:
            t = self.topics[index]
            if not t.incompatible:
                return ''
            kinds = sorted(set(t.incompatible))
            return (f'{len(t.incompatible)} of {t.publishers} publisher(s) with incompatible '
                    f'QoS ({"; ".join(kinds)})')

    def values(self, index: int) -> dict[str, Any]:
        """Diagnostics key-values of topic `index`."""
        with self._lock:
            t = self.topics[index]
            return {'qos_reliability': t.reliability, 'qos_setting': t.setting,
                    'publishers': t.publishers, 'incompatible_publishers': len(t.incompatible),
                    'incompatible_qos_events': t.events, 'resubscribed': t.resubscribed}

    def total_events(self) -> int:
        with self._lock:
            return sum(t.events for t in self.topics)
