"""
The benchmark's child processes: started, read line by line, measured, always killed.

Every child runs in a ROS domain of its own on localhost (:class:`Domains`). The
helper nodes are the ``node_*.py`` files beside this one (:func:`helper`); the
kf_train nodes start as a user starts them (:func:`node_command`).
"""

import json
import math
import os
import queue
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from typing import Dict, List, Optional, Tuple

HERE = os.path.dirname(os.path.abspath(__file__))


class Child:
    """A child process whose stdout lines are collected by a thread; stderr to a file."""

    def __init__(self, argv: List[str], env: Dict[str, str], name: str):
        """Start ``argv``."""
        self.name = name
        self.stderr = tempfile.TemporaryFile(mode='w+')
        self.start_ns = time.time_ns()
        self.process = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE,
                                        stderr=self.stderr, text=True)
        self.lines: 'queue.Queue[str]' = queue.Queue()
        self.all_lines: List[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        """Collect stdout lines."""
        for line in self.process.stdout:
            line = line.rstrip('\n')
            self.all_lines.append(line)
            self.lines.put(line)

    def wait_for(self, prefix: str, timeout_s: float) -> str:
        """Return the first new stdout line starting with ``prefix``; raise on timeout."""
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0.0:
                raise TimeoutError(f'{self.name}: no {prefix!r} line within {timeout_s} s; '
                                   f'stderr: {self.stderr_text()[-400:]!r}')
            try:
                line = self.lines.get(timeout=min(remaining, 0.2))
            except queue.Empty:
                if self.process.poll() is not None and self.lines.empty():
                    raise RuntimeError(f'{self.name} exited with {self.process.returncode} '
                                       f'before {prefix!r}; stderr: '
                                       f'{self.stderr_text()[-400:]!r}') from None
                continue
            if line.startswith(prefix):
                return line

    def json_result(self, timeout_s: float) -> dict:
        """Wait for the process to end; return the last JSON line it printed."""
        self.process.wait(timeout=timeout_s)
        self._reader.join(timeout=2.0)
        for line in reversed(self.all_lines):
            if line.startswith('{'):
                return json.loads(line)
        raise RuntimeError(f'{self.name} printed no result; stderr: '
                           f'{self.stderr_text()[-400:]!r}')

    def stderr_text(self) -> str:
        """Return everything the process wrote to stderr so far."""
        self.stderr.flush()
        self.stderr.seek(0)
        return self.stderr.read()

    def cpu_s(self) -> float:
        """Return the process's user + system CPU time so far [s], from /proc."""
        with open(f'/proc/{self.process.pid}/stat') as stat:
            fields = stat.read().rsplit(')', 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')

    def peak_rss_mib(self) -> float:
        """Return the process's peak resident set size [MiB] (VmHWM)."""
        with open(f'/proc/{self.process.pid}/status') as status:
            for line in status:
                if line.startswith('VmHWM:'):
                    return int(line.split()[1]) / 1024.0
        return math.nan

    def stop(self, signum: int, timeout_s: float = 10.0) -> Tuple[Optional[int], float]:
        """Send ``signum``; return (exit code or None if it had to be killed, seconds)."""
        start = time.monotonic()
        if self.process.poll() is None:
            self.process.send_signal(signum)
        try:
            code = self.process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
            code = None
        return code, time.monotonic() - start

    def kill(self) -> None:
        """Kill the process if it still runs."""
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait()


class Domains:
    """Hands out ROS domain ids for the children, one per trial."""

    def __init__(self):
        """Start from a base derived from the process id."""
        self._next = os.getpid() % 100

    def env(self) -> Dict[str, str]:
        """Return an environment confined to a fresh domain on localhost."""
        self._next = self._next % 100 + 1
        env = dict(os.environ)
        env.update(ROS_DOMAIN_ID=str(self._next), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
                   PYTHONUNBUFFERED='1')
        env.pop('ROS_STATIC_PEERS', None)
        return env


def node_command(node: str) -> List[str]:
    """Return the command that starts a kf_train node as a user would."""
    script = shutil.which(node, path=os.path.dirname(sys.executable))
    if script is not None:
        return [script]
    return [sys.executable, '-m', f'kf_train.ros.{node}_node']


def helper(role: str, *args) -> List[str]:
    """Return the command of a helper node: ``node_<role>.py`` beside this file."""
    return [sys.executable, os.path.join(HERE, f'node_{role}.py')] + [str(a) for a in args]
