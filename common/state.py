"""``racecav state [--car car0] [SERVICE] [--json]``: live services and their status."""

from __future__ import annotations

import argparse
import json
import sys

from racecav.common.config import Config


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("service", nargs="?", help="only this service")
    p.add_argument("--car", help="car name (default: bus.car)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--timeout", type=float, default=1.0, help="seconds to wait for answers")


def collect(session, car: str, only: str | None, timeout: float) -> list[dict]:
    from racecav.common.client import get_status, live_services

    rows = []
    for name in live_services(session, car, timeout):
        if only and name != only:
            continue
        try:
            rows.append({"service": name, "alive": True, **get_status(session, car, name, timeout).model_dump(mode="json")})
        except RuntimeError as e:
            rows.append({"service": name, "alive": True, "error": str(e)})
    return rows


def run(args: argparse.Namespace, cfg: Config) -> int:
    from racecav.common.client import open_session

    import zenoh

    car = args.car or cfg.bus.car
    try:
        session = open_session(cfg)
    except zenoh.ZError as e:  # no router there, or (deployed car) a missing/wrong login or certificate
        login = f"as user {cfg.bus.user!r}" if cfg.bus.user else "without a login (bus.user)"
        print(f"racecav state: cannot join the bus at {', '.join(cfg.bus.connect)} {login}: {e}", file=sys.stderr)
        return 1
    with session:
        rows = collect(session, car, args.service, args.timeout)
    if args.json:
        json.dump({"car": car, "services": rows}, sys.stdout, indent=2)
        print()
    else:
        cols = ["service", "pid", "uptime_s", "received", "published", "invalid", "dropped", "last_error"]
        print(f"car {car}: {len(rows)} live service(s)")
        print(" ".join(f"{c:>10}" if c != "last_error" else c for c in cols))
        for r in rows:
            cells = []
            for c in cols:
                v = r.get(c, "")
                v = f"{v:.0f}" if isinstance(v, float) else str(v)
                cells.append(v[:60] if c == "last_error" else f"{v:>10}")
            print(" ".join(cells))
            if r.get("info"):
                print(f"{'':>10} info: {json.dumps(r['info'])[:200]}")
    if args.service and not rows:
        print(f"racecav state: no live service {args.service!r} on car {car}", file=sys.stderr)
        return 1
    return 0
