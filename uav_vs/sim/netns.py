"""Network namespaces (`ip netns`): a separate network stack per simulated host.

Needs root. SITL runs in one with only its loopback (uav_vs.sim.sitl_process); the two
hosts of uav_vs.sim.radio_link are two, joined by the radio link.
"""
import os
import subprocess


def add(name: str) -> None:
    """Create namespace `name` with its loopback up."""
    if os.geteuid() != 0:
        raise PermissionError(f'network namespace {name} needs root')
    subprocess.run(['ip', 'netns', 'add', name], check=True, capture_output=True)
    subprocess.run(['ip', '-n', name, 'link', 'set', 'dev', 'lo', 'up'], check=True,
                   capture_output=True)


def delete(name: str) -> None:
    """Remove the namespace's name (it ends when the last process in it exits)."""
    subprocess.run(['ip', 'netns', 'del', name], capture_output=True)


def exec_prefix(name: str) -> list[str]:
    """argv prefix that runs a command inside namespace `name`."""
    return ['ip', 'netns', 'exec', name]
