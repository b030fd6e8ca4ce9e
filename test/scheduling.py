"""How the suite's modules are shared between the xdist workers (--dist loadscope, -n 3):
whole modules, as loadscope hands them out, by what they ask of the machine.

- heavy (conftest.HEAVY: whole graphs flown in real time, node storms on both cores): only
  the first worker, one after the other; once they are done it helps with the rest;
- waiting (conftest.WAITING: real-time MAVLink exchanges with the simulated vehicle, which
  sleep for most of their time): only the last worker, when there are three or more, and
  nothing else there, so that a heavy module shares the two cores with one other at most;
- every other module: the workers in between.

With two workers the waiting modules are ordinary ones."""
from pathlib import Path

from xdist.scheduler import LoadScopeScheduling


class HeavyApartScheduling(LoadScopeScheduling):
    heavy: frozenset[str] = frozenset()
    waiting: frozenset[str] = frozenset()

    def _kind(self, scope: str) -> str:
        stem = Path(scope.split('::')[0]).stem
        if stem in self.heavy:
            return 'heavy'
        if stem in self.waiting and len(self.nodes) > 2:
            return 'waiting'
        return 'other'

    def _role(self, node) -> str:
        if node is self.nodes[0]:
            return 'heavy'
        if len(self.nodes) > 2 and node is self.nodes[-1]:
            return 'waiting'
        return 'other'

    def _assign_work_unit(self, node) -> None:
        role = self._role(node)
        scope = next((s for s in self.workqueue if self._kind(s) == role), None)
        if scope is None and role != 'waiting':   # its own are done: help with the rest
            scope = next((s for s in self.workqueue if self._kind(s) != 'heavy'), None)
        if scope is None:      # only heavy or waiting modules left: they stay with theirs
            return
        work_unit = self.workqueue.pop(scope)
        self.assigned_work.setdefault(node, {})[scope] = work_unit
        collection = self.registered_collections[node]
        node.send_runtest_some([collection.index(nodeid)
                                for nodeid, done in work_unit.items() if not done])
