"""ThrottledWarnings: one warning per kind of defect per period, kinds independent."""
from uav_vs.ros import node_main
from uav_vs.ros.node_main import ThrottledWarnings


class FakeLogger:
    def __init__(self) -> None:
        self.warnings: list[str] = []

    def warn(self, text: str) -> None:
        self.warnings.append(text)


class FakeNode:
    def __init__(self) -> None:
        self.logger = FakeLogger()

    def get_logger(self) -> FakeLogger:
        return self.logger


def test_one_warning_per_kind_per_period_and_kinds_do_not_hide_each_other(monkeypatch):
    clock = [100.0]
    monkeypatch.setattr(node_main.time, 'monotonic', lambda: clock[0])
    node = FakeNode()
    warnings = ThrottledWarnings(node, period_s=5.0)

    def at(t: float, kind: str, text: str) -> None:
        clock[0] = 100.0 + t
        warnings.warn(kind, text)

    at(0.0, 'encoding', 'enc 1')
    at(0.1, 'encoding', 'enc 2')        # same kind inside the period: dropped
    at(0.2, 'size', 'size 1')           # another kind: not hidden by the first
    at(4.9, 'encoding', 'enc 3')        # still inside encoding's period
    at(5.0, 'encoding', 'enc 4')        # period over: logged again
    at(5.1, 'size', 'size 2')           # size's period (from 0.2) ends at 5.2
    at(5.2, 'size', 'size 3')
    at(9.9, 'encoding', 'enc 5')        # the period restarts at the last logged one (5.0)
    at(10.0, 'encoding', 'enc 6')
    assert node.logger.warnings == ['enc 1', 'size 1', 'enc 4', 'size 3', 'enc 6']
