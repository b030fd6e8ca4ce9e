"""What a bag replay publishes, under which names and when (no ROS here).

The ROS side (uav_vs.nodes.bag_player) opens a Bag, builds a Plan from the command
line, creates one publisher per `Plan.topics` entry under `Plan.name(topic)` and
publishes every message of `Plan.schedule()` once its due time has come.

A bag topic whose name ROS 2 does not allow (ROS 1 allows more, e.g. `/ORB-SLAM/pose`)
is played under `ros2_name(topic)` unless a remap names it.
"""
import re
from dataclasses import dataclass, field
from itertools import count
from typing import Iterable, Iterator

from uav_vs.bag.reader import Bag, BagError, BagMessage, TopicInfo


@dataclass(frozen=True)
class PlayOptions:
    rate: float = 1.0                       # 0: as fast as the subscribers take it
    start_s: float = 0.0                    # skip this much of the bag's beginning
    duration_s: float | None = None         # play this much bag time (None: to the end)
    loop: bool = False
    topics: tuple[str, ...] | None = None   # None: every topic
    remap: dict[str, str] = field(default_factory=dict)   # bag topic -> published name

    def __post_init__(self) -> None:
        too_short = self.duration_s is not None and self.duration_s <= 0
        if self.rate < 0 or self.start_s < 0 or too_short:
            raise ValueError('rate and start must be >= 0 and duration > 0')


def parse_remaps(items: Iterable[str]) -> dict[str, str]:
    """['old:=new', ...] -> {'old': 'new'}; raises ValueError on a malformed item."""
    out = {}
    for item in items:
        old, sep, new = item.partition(':=')
        if not sep or not old or not new:
            raise ValueError(f'remap {item!r} is not of the form old:=new')
        out[old] = new
    return out


_NOT_IN_ROS2_NAMES = re.compile(r'[^A-Za-z0-9_/]')


def ros2_name(topic: str) -> str:
    """`topic` made a legal ROS 2 name: every character but letters, digits, '_' and '/'
    becomes '_', a token starting with a digit gets a leading '_', empty tokens ('//', a
    trailing '/') go. A legal ROS 2 name is returned as it is."""
    tokens = [t for t in _NOT_IN_ROS2_NAMES.sub('_', topic).split('/') if t]
    name = '/'.join(f'_{t}' if t[0].isdigit() else t for t in tokens) or '_'
    return f'/{name}' if topic.startswith('/') else name


def _key(topic: str) -> str:
    """Names given on the command line match bag topics with or without a leading slash."""
    return topic.lstrip('/')


class Plan:
    """The topics, names and timing of one replay of `bag` with `options`."""

    def __init__(self, bag: Bag, options: PlayOptions) -> None:
        self.bag, self.options = bag, options
        by_key = {_key(t): t for t in bag.topics}
        if options.topics is None:
            chosen = list(bag.topics)
        else:
            missing = [t for t in options.topics if _key(t) not in by_key]
            if missing:
                raise BagError(f'{bag.path}: no topic {", ".join(missing)} in the bag '
                               f'(it has {", ".join(sorted(bag.topics))})')
            chosen = [by_key[_key(t)] for t in options.topics]
        unused = [t for t in options.remap if _key(t) not in by_key]
        if unused:
            raise BagError(f'{bag.path}: remap of {", ".join(unused)}: no such topic in the bag')
        self.topics: dict[str, TopicInfo] = {t: bag.topics[t] for t in chosen}
        remapped = {by_key[_key(old)]: new for old, new in options.remap.items()}
        self.renamed = {t: ros2_name(t) for t in chosen
                        if t not in remapped and ros2_name(t) != t}   # by the ROS 2 name rule
        self._names = {**self.renamed, **remapped}
        self._check_unique()
        self.start_ns = bag.start_ns + round(options.start_s * 1e9)
        end_ns = bag.end_ns if options.duration_s is None else min(
            bag.end_ns, self.start_ns + round(options.duration_s * 1e9))
        self.span_ns = max(end_ns - self.start_ns, 0)      # bag time of one pass
        self._end_ns = end_ns

    def name(self, topic: str) -> str:
        """The name `topic` is published under."""
        return self._names.get(topic, topic)

    def _check_unique(self) -> None:
        """Raise BagError if two chosen topics would be published under one name."""
        by_name: dict[str, list[str]] = {}
        for topic in self.topics:
            by_name.setdefault(_key(self.name(topic)), []).append(topic)
        for topics in by_name.values():
            if len(topics) > 1:
                raise BagError(f'{self.bag.path}: topics {" and ".join(topics)} would both be '
                               f'played as {self.name(topics[-1])}: --remap one of them')

    def due_s(self, pass_index: int, t_ns: int) -> float:
        """Seconds after play start at which a message recorded at t_ns is due."""
        if self.options.rate == 0:
            return 0.0
        return (pass_index * self.span_ns + t_ns - self.start_ns) / 1e9 / self.options.rate

    def bag_time_ns(self, elapsed_s: float) -> int:
        """The bag time (for /clock) `elapsed_s` after play start, at a rate > 0."""
        t = round(elapsed_s * self.options.rate * 1e9)
        if self.options.loop and self.span_ns:
            t %= self.span_ns
        return self.start_ns + min(t, self.span_ns)

    def schedule(self) -> Iterator[tuple[float, BagMessage]]:
        """(due_s, message) for every message to publish, in order; endless with `loop`.

        Raises BagError if a pass yields nothing: the window holds no message of the
        chosen topics, or the bag does not hold what it promises.
        """
        for k in count() if self.options.loop else range(1):
            n = 0
            for msg in self.bag.messages(self.topics, self.start_ns, self._end_ns):
                n += 1
                yield self.due_s(k, msg.t_ns), msg
            if n == 0:
                raise BagError(f'{self.bag.path}: no message of {", ".join(self.topics)} '
                               f'between {self.options.start_s} s and the end of the window')


def progress_line(elapsed_ns: int, span_ns: int, published: int, width: int = 30) -> str:
    """A one-line progress bar: `[#####-----]  50.0 %   3.95 / 7.90 s   280 msgs`."""
    frac = min(max(elapsed_ns / span_ns, 0.0), 1.0) if span_ns > 0 else 1.0
    bar = '#' * round(frac * width)
    return (f'[{bar:-<{width}}] {100 * frac:5.1f} %  {elapsed_ns / 1e9:7.2f} / '
            f'{span_ns / 1e9:.2f} s  {published} msgs')
