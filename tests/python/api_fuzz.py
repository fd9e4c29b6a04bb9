#!/usr/bin/env python3
"""Fuzzes the portal's HTTP API with schemathesis (PyPI): requests generated
from /api/v1/openapi.json, every answer checked against it.

    api_fuzz.py HOST:PORT --user ROLE:NAME:PASSWORD ... [--max-examples N]
                [--seed S] [--forbid TEXT ...] [--report DIR]

Logs every user in first (the fuzzer's own failed logins would otherwise
rate-limit them), then runs schemathesis once per user and once without a
login, over every operation but two: `POST /logout` (it would end the
session the run uses: it is called once per user at the end, and its
answers checked) and `GET /events` (a stream that never ends: a request
cannot complete). Checks: no 5xx (`not_a_server_error`), documented status
codes, content types and response schemas, and `no_server_path` (no answer
contains a --forbid text: the store's folder, the cache, the repository).

Prints one JSON line: per run, the test cases generated and the failures;
exits 1 if any run failed.
"""

import argparse
import json
import os
import re
import subprocess
import sys
import urllib.error
import urllib.request

HERE = os.path.dirname(os.path.abspath(__file__))
CHECKS = "not_a_server_error,status_code_conformance,content_type_conformance,response_schema_conformance,no_server_path"
EXCLUDED = ["/api/v1/logout", "/api/v1/events", "/api/v1/lab/events"]


def call(portal, method, path, token=None, body=None):
    request = urllib.request.Request(f"http://{portal}{path}", data=body, method=method)
    if token:
        request.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            return response.status, response.read()
    except urllib.error.HTTPError as err:
        return err.code, err.read()


def login(portal, name, password):
    status, body = call(portal, "POST", "/api/v1/login", body=json.dumps({"name": name, "password": password}).encode())
    if status != 200:
        sys.exit(f"api_fuzz: login of {name}: {status} {body[:200]!r}")
    return json.loads(body)["token"]


def run(args, label, token):
    """One schemathesis run; (test cases, failures, its output's tail)."""
    command = [
        os.path.join(os.path.dirname(sys.executable), "schemathesis"), "--no-color", "run",
        f"http://{args.portal}/api/v1/openapi.json",
        "--checks", CHECKS, "--max-examples", str(args.max_examples), "--seed", str(args.seed),
        "--workers", "1", "--request-timeout", "60", "--suppress-health-check", "all",
    ]
    for path in EXCLUDED:
        command += ["--exclude-path", path]
    if token:
        command += ["--header", f"Authorization: Bearer {token}"]
    if args.max_time:
        command += ["--max-time", str(args.max_time)]
    if args.report:
        os.makedirs(args.report, exist_ok=True)
        command += ["--report", "junit", "--report-junit-path", os.path.join(args.report, f"{label}.xml")]
    env = {**os.environ, "SCHEMATHESIS_HOOKS": "api_fuzz_hooks", "API_FUZZ_FORBIDDEN": "\n".join(args.forbid),
           "PYTHONPATH": HERE + os.pathsep + os.environ.get("PYTHONPATH", "")}
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    output = done.stdout + done.stderr
    generated = re.search(r"(\d+) generated", output)
    failed = done.returncode != 0
    return {"run": label, "generated": int(generated.group(1)) if generated else 0, "failed": failed,
            "output": output[-6000:] if failed else ""}


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("portal")
    parser.add_argument("--user", action="append", default=[], help="ROLE:NAME:PASSWORD")
    parser.add_argument("--max-examples", type=int, default=20)
    parser.add_argument("--max-time", type=int, default=0, help="seconds per run (0: no bound)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--forbid", action="append", default=[])
    parser.add_argument("--report", default="")
    args = parser.parse_args()
    users = [u.split(":", 2) for u in args.user]
    tokens = [(role, login(args.portal, name, password)) for role, name, password in users]
    results = [run(args, "anonymous", None)]
    for role, token in tokens:
        results.append(run(args, role, token))
    # POST /logout, left out of the runs: ends the session once (204), then
    # the same token is no longer a session (401).
    for role, token in tokens:
        first, _ = call(args.portal, "POST", "/api/v1/logout", token)
        second, _ = call(args.portal, "POST", "/api/v1/logout", token)
        ok = (first, second) == (204, 401)
        results.append({"run": f"{role} logout", "generated": 2, "failed": not ok,
                        "output": "" if ok else f"logout answered {first}, then {second}"})
    for result in results:
        if result["failed"]:
            print(f"==> {result['run']} failed:\n{result['output']}", file=sys.stderr)
    print(json.dumps({"runs": [{k: r[k] for k in ("run", "generated", "failed")} for r in results]}))
    sys.exit(1 if any(r["failed"] for r in results) else 0)


if __name__ == "__main__":
    main()
