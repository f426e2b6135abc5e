"""The ``ardflow`` command line: the parser and the entry point; the commands live in
:mod:`.cmd_local` (models, data, examples), :mod:`.cmd_study` (studies, the closed loop) and
:mod:`.cmd_remote` (the service and its client).

Every user error is printed as one ``error: ...`` line with exit status 2;
tracebacks are for bugs only.
"""

from __future__ import annotations

import argparse
import sys

from ardflow.ardcore.loop.config import DiagnoseConfig

from ardflow.service.commands.local import (
    cmd_data, cmd_example, cmd_loglik, cmd_models, cmd_settings, cmd_simulate,
)
from ardflow.service.commands.remote import cmd_fetch, cmd_serve, cmd_status, cmd_submit
from ardflow.service.commands.study import cmd_demo, cmd_diagnose, cmd_loo, cmd_resume, cmd_select


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="ardflow", description="Bayesian model selection for stochastic dynamical systems")
    sub = p.add_subparsers(dest="cmd", required=True)
    _local_commands(sub)
    _study_commands(sub)
    _service_commands(sub)
    return p


def _local_commands(sub) -> None:
    """Commands on models, data, examples and settings on this machine."""
    s = sub.add_parser("simulate", help="simulate the reference data set or any model to CSV (+ JSON sidecar)")
    s.add_argument("model", help="'reference' (the paper's pipeline), a built-in model name, or a model JSON file")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", required=True)
    s.add_argument("--param", action="append", metavar="NAME=VALUE", help="parameter value (models other than reference)")
    s.add_argument("--n", type=int, default=5000, help="number of samples")
    s.add_argument("--dt", type=float, default=0.1, help="sampling interval")
    s.add_argument("--nsub", type=int, default=100, help="Euler-Maruyama steps per sample")
    s.add_argument("--input-std", type=float, default=1.0, help="std of the random input of forced models")
    s.set_defaults(fn=cmd_simulate)

    s = sub.add_parser("loglik", help="EKF log-likelihood of a model on a data set")
    s.add_argument("data")
    s.add_argument("--model", required=True)
    s.add_argument("--param", action="append", metavar="NAME=VALUE")
    s.add_argument("--substeps", type=int, default=None)
    s.add_argument("--fs", type=float, default=None, help="sampling frequency when the file has no 't' column")
    s.add_argument("--rename", action="append", metavar="OLD=NEW")
    s.set_defaults(fn=cmd_loglik)

    s = sub.add_parser("data", help="check or convert a data file (CSV, NPZ, MAT)")
    s.add_argument("action", choices=["check", "convert"])
    s.add_argument("data")
    s.add_argument("--fs", type=float, default=None)
    s.add_argument("--rename", action="append", metavar="OLD=NEW")
    s.add_argument("--out", default=None, help="CSV to write (convert)")
    s.set_defaults(fn=cmd_data)

    s = sub.add_parser("models", help="list the built-in models, or print one as JSON")
    s.add_argument("name", nargs="?")
    s.set_defaults(fn=cmd_models)

    s = sub.add_parser("example", help="list the example study specs, or write one out")
    s.add_argument("name", nargs="?")
    s.add_argument("--out", help="file to write (default: print it)")
    s.set_defaults(fn=cmd_example)

    s = sub.add_parser("settings", help="the sampler's and maximiser's settings: defaults, bounds, meaning")
    s.add_argument("section", nargs="?", choices=["sampler", "maximiser"])
    s.set_defaults(fn=cmd_settings)


def _study_commands(sub) -> None:
    """Studies, the closed loop and the demo (embedded cluster, a process pool or an existing scheduler)."""
    s = sub.add_parser("select", help="run a model-selection study (JSON spec); the zarr store and "
                                      "summary.json go to --out")
    s.add_argument("spec")
    s.add_argument("--out", required=True, help="study store directory (zarr) with summary.json")
    s.add_argument("--executor", choices=["dask", "processes", "serial"], default="dask",
                   help="dask (default: embedded LocalCluster or --scheduler), a local process pool, or serial")
    s.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler")
    s.add_argument("--workers", type=int, default=None, help="embedded cluster / pool size (default: cores)")
    s.add_argument("--performance-report", default=None, metavar="FILE.html", help="write Dask's performance report")
    s.add_argument("--full", action="store_true", help="paper-scale sampler settings")
    s.set_defaults(fn=cmd_select)

    s = sub.add_parser("resume", help="continue a study whose driver stopped")
    s.add_argument("store")
    s.add_argument("--scheduler", default=None)
    s.add_argument("--workers", type=int, default=None)
    s.add_argument("--performance-report", default=None, metavar="FILE.html")
    s.set_defaults(fn=cmd_resume)

    s = sub.add_parser("diagnose", help="close the loop: find the residual of a fitted model, trace it to a "
                                        "missing effect, add it under ARD and report the error before and after")
    s.add_argument("spec", help="study spec (JSON) or a finished study store; one model (--model, default the "
                                "spec's only model or the study's best) is diagnosed")
    s.add_argument("--out", required=True, help="directory for diagnosis.json, diagnosis.html and figures")
    s.add_argument("--model", help="which candidate of the spec to diagnose")
    s.add_argument("--test-start", type=int, help="first row of the held-out record for the free run "
                                                  "(rows of the same file; default: the estimation data)")
    s.add_argument("--test-stop", type=int, help="end row of the held-out record")
    s.add_argument("--test-data", action="append",
                   help="held-out record in its own file (same columns as the data); repeat it for several records")
    s.add_argument("--test-rename", action="append", metavar="OLD=NEW",
                   help="renaming of the held-out file's columns (default: the spec's data.rename); e.g. "
                        "--test-rename uVal=u --test-rename yVal=y for a file that holds both records")
    s.add_argument("--seed", type=int, help="the loop's random numbers (its starts and draws) at this seed instead "
                                            "of the spec's: a model found at two seeds does not owe itself to one "
                                            "run's path")
    for name in ("top_k", "max_rounds"):  # the loop's own defaults and words
        f = DiagnoseConfig.model_fields[name]
        s.add_argument("--" + name.replace("_", "-"), type=int, default=f.default,
                       help=f"{f.description} (default {f.default})")
    s.set_defaults(fn=cmd_diagnose)

    s = sub.add_parser("loo", help="PSIS-LOO of every model of a finished study beside its evidence (ArviZ)")
    s.add_argument("store", help="a finished study's store")
    s.add_argument("--draws", type=int, default=1000, help="posterior draws for the pointwise log-likelihood "
                                                           "(one EKF pass each; default 1000)")
    s.add_argument("--json", metavar="FILE", help="also write the table as JSON")
    s.set_defaults(fn=cmd_loo)

    s = sub.add_parser("demo", help="the main job: the Section 3.6 study on an embedded cluster, with its report")
    s.add_argument("--out", default="runs/demo")
    s.add_argument("--full", action="store_true", help="paper-scale sampler settings")
    s.add_argument("--spec", default=None, help="a Section 3.6 spec in place of examples/sec36.json (other "
                                                "settings; the checks use its true_values)")
    s.add_argument("--workers", type=int, default=None)
    s.add_argument("--scheduler", default=None)
    s.add_argument("--performance-report", default=None, metavar="FILE.html")
    s.set_defaults(fn=cmd_demo)


def _service_commands(sub) -> None:
    """The REST service and its remote client commands."""
    s = sub.add_parser("serve", help="run the REST API (embedded LocalCluster or --scheduler)")
    s.add_argument("--host", default="127.0.0.1")
    s.add_argument("--port", type=int, default=8000)
    s.add_argument("--root", default="runs/service", help="registry directory (studies and data sets)")
    s.add_argument("--token", default=None,
                   help="API token (default: $ARDFLOW_TOKEN, else generated into ROOT/token)")
    s.add_argument("--insecure-no-auth", action="store_true",
                   help="no token (loopback only: any local process can then submit studies)")
    s.add_argument("--max-running", type=int, default=2, help="study drivers at once; the others wait queued")
    s.add_argument("--tokens-file", default=None,
                   help='JSON {"owner": "token", ...}: one token per user, each limited separately')
    s.add_argument("--scheduler", default=None)
    s.add_argument("--workers", type=int, default=None)
    s.add_argument("--max-body-mb", type=float, default=20.0)
    s.add_argument("--forwarded-allow-ips", default=None, metavar="IPS",
                   help="reverse proxies whose X-Forwarded-For/-Proto are believed (comma-separated; default none)")
    s.add_argument("--max-connections", type=int, default=1000,
                   help="open connections at most; more are answered 503 (default 1000)")
    s.add_argument("--header-timeout", type=float, default=10.0,
                   help="seconds a connection may take to send a request's headers; then it is closed (default 10)")
    s.set_defaults(fn=cmd_serve)

    for name, fn, hlp in (("submit", cmd_submit, "submit a study to a running service"),
                          ("status", cmd_status, "status of one study (or the list)"),
                          ("fetch", cmd_fetch, "download a finished study's summary, posteriors and figures")):
        s = sub.add_parser(name, help=hlp)
        if name == "submit":
            s.add_argument("spec")
            s.add_argument("--csv", default=None, action="append",
                           help="upload this CSV as the study's data set (repeat it, one per record, for a study of "
                                "several records)")
            s.add_argument("--wait", action="store_true")
        elif name == "status":
            s.add_argument("id", nargs="?")
            s.add_argument("--json", action="store_true", help="the service's JSON, for scripts")
        else:
            s.add_argument("id")
            s.add_argument("--out", required=True)
        s.add_argument("--url", default=None,
                       help="the service (default: $ARDFLOW_URL, else http://127.0.0.1:8000, where `ardflow serve` "
                            "listens)")
        s.add_argument("--token", default=None,
                       help="API token (default: $ARDFLOW_TOKEN, else runs/service/token, which `ardflow serve` "
                            "writes)")
        s.set_defaults(fn=fn)


def main(argv: list[str] | None = None) -> int:
    from ardflow.ardcore.errors import ArdflowError
    from pydantic import ValidationError

    args = build_parser().parse_args(argv)
    if args.cmd == "data" and args.action == "convert" and not args.out:
        print("error: data convert needs --out FILE.csv", file=sys.stderr)
        return 2
    try:
        return args.fn(args)
    except ArdflowError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except ValidationError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 - only the service's transport errors are caught here
        import httpx

        if not isinstance(exc, httpx.TransportError):
            raise
        url = getattr(args, "url", None) or "the service"
        print(f"error: cannot reach the ardflow service at {url} ({type(exc).__name__}: {exc}). Start one with "
              "`ardflow serve`, or point the client elsewhere with --url or ARDFLOW_URL (token: --token, "
              "ARDFLOW_TOKEN or runs/service/token)", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
