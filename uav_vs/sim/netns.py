"""Network namespaces (`ip netns`): a separate network stack per simulated host.

Needs root. SITL runs in one with only its loopback (uav_vs.sim.sitl_process); the two
hosts of uav_vs.sim.radio_link are two, joined by the radio link.
"""
import ctypes
import os
import subprocess

_CLONE_NEWNET = 0x40000000


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


def enter(name: str) -> None:
    """Move the calling thread into namespace `name`. Call it before any thread or node
    starts: only the calling thread moves, and what it starts afterwards inherits it."""
    libc = ctypes.CDLL(None, use_errno=True)
    with open(f'/var/run/netns/{name}') as ns:
        if libc.setns(ns.fileno(), _CLONE_NEWNET) != 0:
            raise OSError(ctypes.get_errno(), f'setns into {name}')
