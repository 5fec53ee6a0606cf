"""``mateqa schedule``: a library's night every night, as a Prefect deployment.

``add NAME --library DIR --cron "0 2 * * *"`` (and any option of ``nightly``) writes the
deployment ``nightly/NAME`` (``flows.schedules``), ``set NAME ...`` changes the options given
and keeps the rest, ``list``, ``show NAME`` and ``remove NAME`` read and delete them. Each
schedule has its own workspace, so several libraries run side by side, each with its history.
The commands talk to the Prefect server of ``PREFECT_API_URL``, else to the local one
(``MATEQA_SERVER_PORT``) that ``mateqa serve`` keeps up; its worker runs the nights.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from flows.cli_options import add_config_options, dest

if TYPE_CHECKING:
    from flows.schedules import Schedule


def add_schedule_parser(sub: argparse._SubParsersAction, tolerances: Any) -> None:  # type: ignore[type-arg]
    """The ``schedule`` command and its actions; ``tolerances`` adds ``--tol``/``--tolerances``."""
    p = sub.add_parser("schedule", help="run a library's night every night (Prefect "
                       "deployments)", description=__doc__.split("\n\n")[1].replace("\n", " "))
    actions = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    for action, text in (("add", "schedule a library's night: the deployment nightly/NAME"),
                         ("set", "change the options given of a schedule, keep the rest")):
        q = actions.add_parser(action, help=text, description=text + ". Every option of "
                               "`mateqa nightly` is taken; the workspace defaults to a folder "
                               "NAME in the current one. Paths are made absolute.")
        add_config_options(q, f"schedule {action}")
        for option in q._actions:  # a schedule's workspace is its own unless given
            if option.dest == dest("runtime.workspace"):
                option.help = ("the workspace folder, the schedule's own (default: a folder "
                               "NAME in the current one; set: unchanged)")
        tolerances(q)
        q.set_defaults(func=cmd_schedule, command=f"schedule {action}")
    q = actions.add_parser("list", help="the schedules: cron, next and last run, workspace")
    q.set_defaults(func=cmd_schedule, command="schedule list", tol=[], tolerances_file=None)
    for action, text in (("show", "one schedule: its night's options and its runs"),
                         ("remove", "delete a schedule (its workspace and reports stay)")):
        q = actions.add_parser(action, help=text, description=text + ".")
        q.add_argument("name", metavar="NAME", help="the schedule's name")
        q.set_defaults(func=cmd_schedule, command=f"schedule {action}", tol=[],
                       tolerances_file=None)


def cmd_schedule(args: argparse.Namespace) -> int:
    from flows.config import ConfigError
    from flows.schedules import ScheduleError

    url = _api_url()
    if url is None:
        return 1
    try:
        return int(_ACTIONS[args.action](args, url))
    except ConfigError as exc:
        print(f"mateqa {args.command}: {exc}", file=sys.stderr)
        return 2
    except ScheduleError as exc:
        print(f"mateqa {args.command}: {exc}", file=sys.stderr)
        return 1


def _api_url() -> str | None:
    """The Prefect API the schedules live on, when it answers (else None, with the reason).
    A server busy with a night's runs may take seconds to answer: it is given
    ``api_problem``'s ten, not the two a starting server is polled with."""
    import os

    from flows.server import api_problem, api_url
    from flows.settings import load_settings

    url = os.environ.get("PREFECT_API_URL") or api_url(load_settings().server_port)
    problem = api_problem(url)
    if problem is None:
        return url
    print(f"mateqa schedule: no Prefect server answers at {url} ({problem}): start one with "
          "`mateqa serve` (it also runs the worker that starts the nights), or set "
          "PREFECT_API_URL", file=sys.stderr)
    return None


def _add(args: argparse.Namespace, url: str) -> int:
    from flows.schedules import night_values, read_schedules, run

    config = args.config
    if run(url, lambda c: read_schedules(c, config.schedule.name)):
        print(f"mateqa schedule add: a schedule {config.schedule.name!r} exists: change it "
              "with `mateqa schedule set`, or remove it first", file=sys.stderr)
        return 2
    return _write(config, night_values(config, Path.cwd()), url, "added")


def _set(args: argparse.Namespace, url: str) -> int:
    from flows.schedules import night_values, updated

    schedule = _one(url, args.config.schedule.name)
    if schedule is None:
        return 2
    config = updated(schedule, args.config, Path.cwd())
    return _write(config, night_values(config, Path.cwd()), url, "changed")


def _write(config: Any, values: dict[str, Any], url: str, done: str) -> int:
    from flows.schedules import apply, check_night, run
    from flows.server import project_root

    warnings = check_night(config)  # the night's own checks, before the server has it
    warnings += run(url, lambda c: apply(c, config, values, project_root()))
    for warning in warnings:
        print(f"mateqa schedule: warning: {warning}", file=sys.stderr)
    when = config.schedule
    print(f"{done} the schedule {when.name!r}: deployment nightly/{when.name}, cron "
          f"{when.cron!r} ({when.timezone}){'' if when.active else ', paused'}, library "
          f"{values.get('library', {}).get('path') or '(the built-in samples)'}, workspace "
          f"{values['runtime']['workspace']}\nrun it now with `prefect deployment run "
          f"'nightly/{when.name}'`; see it with `mateqa schedule show {when.name}`")
    return 0


def _one(url: str, name: str) -> Schedule | None:
    from flows.schedules import read_schedules, run

    found = run(url, lambda c: read_schedules(c, name))
    if not found:
        print(f"mateqa schedule: no schedule named {name!r} (`mateqa schedule list` lists "
              "them)", file=sys.stderr)
        return None
    return found[0]


def _list(args: argparse.Namespace, url: str) -> int:
    from flows.schedules import read_schedules, run

    found = run(url, read_schedules)
    if not found:
        print(f"no schedules on {url} (add one with `mateqa schedule add NAME --library DIR`)")
        return 0
    rows = [("NAME", "CRON", "ACTIVE", "NEXT RUN", "LAST RUN", "LIBRARY", "WORKSPACE")]
    rows += [(s.name, f"{s.cron} ({s.timezone})", "yes" if s.active else "paused",
              s.next_run or "-", s.last_run or "-", s.library, s.workspace) for s in found]
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    for row in rows:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip())
    return 0


def _show(args: argparse.Namespace, url: str) -> int:
    s = _one(url, args.name)
    if s is None:
        return 2
    print(f"schedule {s.name}: deployment nightly/{s.name}\n"
          f"  cron       {s.cron} ({s.timezone}){'' if s.active else ', paused'}\n"
          f"  library    {s.library}\n  workspace  {s.workspace}\n"
          f"  next run   {s.next_run or '-'}\n  last run   {s.last_run or '-'}\n"
          f"  newest report  {Path(s.workspace) / 'runs' / 'latest' / 'report.html'}\n"
          "  the night's options (every other field takes its default):")
    print("\n".join("    " + line for line in json.dumps(s.config, indent=2).splitlines()))
    return 0


def _remove(args: argparse.Namespace, url: str) -> int:
    from flows.schedules import read_schedules, remove, run

    found = run(url, lambda c: read_schedules(c, args.name))
    if not found or not run(url, lambda c: remove(c, args.name)):
        print(f"mateqa schedule remove: no schedule named {args.name!r}", file=sys.stderr)
        return 2
    print(f"removed the schedule {args.name!r} (deployment nightly/{args.name} and its planned "
          f"runs); its workspace {found[0].workspace} and its reports stay")
    return 0


_ACTIONS = {"add": _add, "set": _set, "list": _list, "show": _show, "remove": _remove}
