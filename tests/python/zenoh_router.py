"""A Zenoh router run by the eclipse-zenoh package (an implementation no one
here wrote) from a JSON5 config file, such as config/zenoh-lab-router.json5
(tests/all/labnet.rs drives it; docs/lab.md shows how to run it).

    zenoh_router.py CONFIG [--listen ENDPOINT] [--users FILE]

Opens a session in router mode from CONFIG (its access_control block
included); --listen replaces its listen endpoints, --users its
user/password dictionary file. Prints "ready" with the router's id once it
listens, then runs until its standard input closes (or forever when it is a
terminal's and Ctrl-C stops it).
"""

import argparse
import json
import sys

import zenoh


def main():
    parser = argparse.ArgumentParser(description="A Zenoh router from a JSON5 config file.")
    parser.add_argument("config")
    parser.add_argument("--listen", help="listen on this endpoint instead of the config's")
    parser.add_argument("--users", help="the user/password dictionary file instead of the config's")
    args = parser.parse_args()
    zenoh.init_log_from_env_or("error")
    conf = zenoh.Config.from_file(args.config)
    conf.insert_json5("mode", json.dumps("router"))
    if args.listen:
        conf.insert_json5("listen/endpoints", json.dumps([args.listen]))
    if args.users:
        conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(args.users))
    session = zenoh.open(conf)
    print(json.dumps({"ready": str(session.zid())}), flush=True)
    try:
        sys.stdin.read()
    except KeyboardInterrupt:
        pass
    session.close()


if __name__ == "__main__":
    main()
