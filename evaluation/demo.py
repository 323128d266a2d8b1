"""``racecav demo``: the README's main command.

Starts the car's router and a sample scan publisher as separate processes, shows
``racecav state`` and stops everything cleanly.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time

from racecav.common.config import Config


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=float, default=3.0, help="how long the sample publisher runs")


def run(args: argparse.Namespace, cfg: Config) -> int:
    from racecav.common import procs

    with procs.router() as endpoint:
        env = procs.bus_env(endpoint)
        echo = procs.start(["echo", "scan", "--quiet"], env)
        pub = subprocess.Popen([sys.executable, "-m", "racecav.common.bench_bus", "--publisher", "60",
                                str(int(60 * args.seconds))], env=env, start_new_session=True)
        try:
            time.sleep(args.seconds + 1.5)
            subprocess.run(procs.racecav_cmd("state"), env=env, check=True)
        finally:
            procs.stop(pub)
            procs.stop(echo)
    return 0
