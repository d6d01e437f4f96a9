#!/usr/bin/env python3
"""Write the Zenoh config of a fleet pool's router: the one door robots and pool workers use.

    deploy/make-certs.sh --out deploy/pool-certs --name POOL_ADDRESS --client robot-robotA --client robot-robotB
    deploy/pool-acl.py --out deploy/pool-certs --pool lab --robot robotA --robot robotB --worker w0 --worker w1
    POOL_ADDRESS=... docker compose -f deploy/pool.compose.yml up -d        # on the pool host

With --out DIR it writes DIR/pool.json5 (the router), DIR/users.txt (a password per user, kept
when the user exists already), DIR/worker-W.json5 (worker W's client config, on the pool host's
private network) and DIR/robot-R.json5 (robot R's link: its internal router connects to the pool
with it, TLS client certificate robot-R.pem from make-certs.sh); without, it prints the router's.

Every link authenticates with a user/password (`usrpwd`, dictionary `users.txt`): robot R connects
as user `robot-R`, worker W as `worker-W` (W is its `--instance`). With --tls (the default) the
router listens on tls/ for the robots, with mutual TLS as well, and on tcp/ for the workers on the
pool host's private network (default tls/0.0.0.0:7449 and tcp/0.0.0.0:7450); --plain listens on
tcp/ only (a private network; the tests).

Access control, default deny, one rule set per robot and per worker:
  robot R  may put only `work/*/R` and `demand/R` (it cannot send work, or ask, in another robot's
           name) and receives only `grant/R/*`, `result/R/*` and `done/R/*` (its own grants and maps),
           the workers' tokens and the pool's stats.
  worker W may subscribe only to `work/W/*` (it sees only the frames sent to it) and the robots'
           demands, and put only `grant/*/W`, `result/*/W`, `done/*/W`, `stats/W` and its tokens
           (it cannot answer in another worker's name).
What Zenoh's access control cannot express, and how the pool covers it:
  * no templates: a rule cannot say "the robot id in the key equals the user's name", so this
    script writes one rule set per robot and per worker; adding one means regenerating the file
    and restarting the router (the existing links reconnect within the lease).
  * no binding of a payload to a key: a robot may put a frame whose StereoFrame.robot_id names
    another robot on its own key: the worker drops it (robot_id must equal the key's).
  * no per-message rates: a robot may put as many frames as its link carries; without a grant
    they are dropped unread (counted as unsolicited) and cost it no share, only bandwidth.
  * a worker computes what it is sent and sees those frames: access control cannot keep a
    robot's frames from the worker it chose to send them to. Trusting a worker with frames is
    the robot's decision; its maps are checked by the robot's dispatcher whatever ACL allows.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import secrets
import sys
from pathlib import Path

NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


def rules_for(pool: str, robots: list[str], workers: list[str]) -> dict:
    p = f"ballbot/pool/{pool}"
    rules, subjects, policies = [], [], []

    def rule(rid: str, flow: str, messages: list[str], keys: list[str]) -> str:
        rules.append({"id": rid, "permission": "allow", "flows": [flow], "messages": messages, "key_exprs": keys})
        return rid

    for r in robots:
        ids = [
            rule(f"robot-{r}-put", "ingress", ["put"], [f"{p}/work/*/{r}", f"{p}/demand/{r}"]),
            rule(f"robot-{r}-sub", "ingress", ["declare_subscriber"],
                 [f"{p}/grant/{r}/*", f"{p}/result/{r}/*", f"{p}/done/{r}/*", f"{p}/stats/*"]),
            rule(f"robot-{r}-live", "ingress", ["declare_liveliness_subscriber", "liveliness_query"],
                 [f"{p}/workers/*", f"{p}/alive/*"]),
            rule(f"robot-{r}-out", "egress", ["put"],
                 [f"{p}/grant/{r}/*", f"{p}/result/{r}/*", f"{p}/done/{r}/*", f"{p}/stats/*"]),
            rule(f"robot-{r}-out-live", "egress", ["liveliness_token", "reply"], [f"{p}/workers/*", f"{p}/alive/*"]),
            # the workers' subscriptions its puts go to (so its publishers know someone listens)
            rule(f"robot-{r}-out-interest", "egress", ["declare_subscriber"], [f"{p}/work/*/*", f"{p}/demand/*"]),
        ]
        subjects.append({"id": f"robot-{r}", "usernames": [f"robot-{r}"]})
        policies.append({"id": f"robot-{r}", "subjects": [f"robot-{r}"], "rules": ids})
    for w in workers:
        ids = [
            rule(f"worker-{w}-sub", "ingress", ["declare_subscriber"], [f"{p}/work/{w}/*", f"{p}/demand/*"]),
            rule(f"worker-{w}-put", "ingress", ["put"],
                 [f"{p}/grant/*/{w}", f"{p}/result/*/{w}", f"{p}/done/*/{w}", f"{p}/stats/{w}"]),
            rule(f"worker-{w}-live", "ingress", ["liveliness_token"], [f"{p}/workers/{w}", f"{p}/alive/{w}"]),
            rule(f"worker-{w}-out", "egress", ["put"], [f"{p}/work/{w}/*", f"{p}/demand/*"]),
            rule(f"worker-{w}-out-interest", "egress", ["declare_subscriber"],
                 [f"{p}/grant/*/*", f"{p}/result/*/*", f"{p}/done/*/*", f"{p}/stats/*"]),
        ]
        subjects.append({"id": f"worker-{w}", "usernames": [f"worker-{w}"]})
        policies.append({"id": f"worker-{w}", "subjects": [f"worker-{w}"], "rules": ids})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def config(pool: str, robots: list[str], workers: list[str], listen: list[str], certs: str, tls: bool) -> dict:
    auth = {"usrpwd": {"dictionary_file": f"{certs}/users.txt"}}
    conf: dict = {"mode": "router", "listen": {"endpoints": listen}, "scouting": {"multicast": {"enabled": False}},
                  "transport": {"auth": auth}, "access_control": rules_for(pool, robots, workers)}
    if tls:
        conf["transport"]["link"] = {"tls": {"root_ca_certificate": f"{certs}/ca.pem",
                                             "listen_certificate": f"{certs}/router.pem",
                                             "listen_private_key": f"{certs}/router.key", "enable_mtls": True}}
    return conf


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pool", required=True)
    ap.add_argument("--robot", action="append", default=[], help="a robot id allowed in the pool (repeat)")
    ap.add_argument("--worker", action="append", default=[], help="a worker instance allowed in the pool (repeat)")
    ap.add_argument("--listen", action="append", default=[], help="repeatable; default tls/0.0.0.0:7449 and "
                    "tcp/0.0.0.0:7450 (--plain: tcp/0.0.0.0:7449)")
    ap.add_argument("--out", default=None, metavar="DIR",
                    help="write pool.json5, users.txt and the clients' configs here")
    ap.add_argument("--certs-path", default="/etc/zenoh-certs", help="where the router sees users.txt (and the "
                    "TLS files)")
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--tls", dest="tls", action="store_true", default=True)
    mode.add_argument("--plain", dest="tls", action="store_false", help="tcp with user/password only")
    a = ap.parse_args(argv)
    for what, names in (("--pool", [a.pool]), ("--robot", a.robot), ("--worker", a.worker)):
        bad = [n for n in names if not NAME.match(n)]
        if bad:
            ap.error(f"{what} {bad[0]!r}: letters, digits, _ . - only (it becomes a key chunk and a user name)")
    if not a.robot or not a.worker:
        ap.error("at least one --robot and one --worker")
    listen = a.listen or (["tls/0.0.0.0:7449", "tcp/0.0.0.0:7450"] if a.tls else ["tcp/0.0.0.0:7449"])
    certs = a.certs_path.rstrip("/")
    text = ("// Generated by deploy/pool-acl.py; regenerate to add a robot or a worker.\n"
            + json.dumps(config(a.pool, a.robot, a.worker, listen, certs, a.tls), indent=2) + "\n")
    if not a.out:
        sys.stdout.write(text)
        return 0
    write_out(Path(a.out), text, a.robot, a.worker, certs, a.tls)
    return 0


def write_out(out: Path, router: str, robots: list[str], workers: list[str], certs: str, tls: bool) -> None:
    out.mkdir(parents=True, exist_ok=True)
    users_file = out / "users.txt"
    users: dict[str, str] = {}
    if users_file.exists():
        for line in users_file.read_text().splitlines():
            if ":" in line:
                u, pw = line.split(":", 1)
                users[u] = pw
    wanted = [f"robot-{r}" for r in robots] + [f"worker-{w}" for w in workers]
    users = {u: users.get(u) or secrets.token_urlsafe(24) for u in wanted}

    def private(path: Path, text: str) -> None:
        path.write_text(text)
        os.chmod(path, 0o640)
        if hasattr(os, "geteuid") and os.geteuid() == 0:
            os.chown(path, -1, 10001)  # the image's user reads it (as make-certs.sh does)

    private(out / "pool.json5", router)
    private(users_file, "".join(f"{u}:{pw}\n" for u, pw in users.items()))
    for w in workers:
        u = f"worker-{w}"
        private(out / f"{u}.json5", json.dumps({"transport": {"auth": {"usrpwd": {"user": u, "password": users[u]}}}},
                                              indent=2) + "\n")
    for r in robots:
        u = f"robot-{r}"
        link: dict = {"transport": {"auth": {"usrpwd": {"user": u, "password": users[u]}}}}
        if tls:
            link["transport"]["link"] = {"tls": {"root_ca_certificate": f"{certs}/ca.pem", "enable_mtls": True,
                                                 "connect_certificate": f"{certs}/{u}.pem",
                                                 "connect_private_key": f"{certs}/{u}.key"}}
        private(out / f"{u}.json5", json.dumps(link, indent=2) + "\n")
    print(f"wrote {out}/pool.json5, users.txt, " + ", ".join(f"{u}.json5" for u in wanted), file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
