"""How the suite's modules are shared between the two xdist workers (--dist loadscope):
whole modules, as loadscope hands them out, but the heavy ones (conftest.HEAVY: whole
graphs flown in real time, node storms on both cores) only to the first worker, one after
the other; the other worker takes every other module, and the first helps with those
once its heavy ones are done."""
from pathlib import Path

from xdist.scheduler import LoadScopeScheduling


class HeavyApartScheduling(LoadScopeScheduling):
    heavy: frozenset[str] = frozenset()

    def _is_heavy(self, scope: str) -> bool:
        return Path(scope.split('::')[0]).stem in self.heavy

    def _assign_work_unit(self, node) -> None:
        first = node is self.nodes[0]
        scope = next((s for s in self.workqueue if self._is_heavy(s) == first), None)
        if scope is None and first:
            scope = next(iter(self.workqueue))
        if scope is None:      # only heavy modules left: they stay with the first worker
            return
        work_unit = self.workqueue.pop(scope)
        self.assigned_work.setdefault(node, {})[scope] = work_unit
        collection = self.registered_collections[node]
        node.send_runtest_some([collection.index(nodeid)
                                for nodeid, done in work_unit.items() if not done])
