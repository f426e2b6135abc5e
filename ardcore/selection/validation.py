"""Complete validation of a study's models: parse, differentiate and generate each kernel's source.

The schema accepts any expression text; what an expression costs shows only when it is differentiated and
turned into a kernel. The service runs :func:`check_study` at submit in a child process with a time and
memory limit (``python -m ardflow.ardcore.selection.validation`` reads the study as JSON on stdin), so a poison model is a 422
naming its field instead of a worker busy forever. Exit status 0: fine; 2: the first line of stderr is the
user's error; anything else: the check itself failed.
"""

from __future__ import annotations

import json
import sys

from ..errors import ArdflowError, ModelError


def parse_models(spec) -> None:
    """Parse every expression of every candidate of ``spec`` (:func:`ardcore.model.declaration.parse_model`: cheap and
    bounded), without differentiating. The service runs this in-process before the child-process check,
    so that most bad models are answered at once."""
    from ..model.declaration import parse_model

    for cand in spec.models:
        parse_model(cand.model_spec())


def check_study(spec) -> None:
    """Parse, differentiate and generate the kernel source of every candidate of ``spec`` (a StudySpec).

    Raises
    ------
    ModelError
        Naming the model and the field of the first expression that cannot become a kernel.
    """
    from ..model.codegen import generate_source

    for i, cand in enumerate(spec.models):
        ms = cand.model_spec()
        try:
            src = generate_source(ms)
            compile(src, f"<kernel {ms.name}>", "exec")
        except ArdflowError:
            raise
        except (RecursionError, MemoryError):
            raise ModelError(f"models[{i}] ({cand.label}): the model is too large to compile") from None
        except (ValueError, TypeError, ArithmeticError, SyntaxError) as exc:
            raise ModelError(f"models[{i}] ({cand.label}): cannot compile the model: {exc}") from None


def main(argv: list[str] | None = None) -> int:
    import argparse

    from .spec import StudySpec

    ap = argparse.ArgumentParser(prog="python -m ardflow.ardcore.selection.validation", description="check a study's models (JSON on stdin)")
    ap.add_argument("--memory-mb", type=int, default=None, help="address-space limit of this process")
    a = ap.parse_args(argv)
    if a.memory_mb:
        import resource

        b = a.memory_mb * 1024 * 1024
        resource.setrlimit(resource.RLIMIT_AS, (b, b))

    try:
        spec = StudySpec.model_validate(json.loads(sys.stdin.read()))
        check_study(spec)
    except ArdflowError as exc:
        print(str(exc).splitlines()[0] if str(exc) else type(exc).__name__, file=sys.stderr)
        return 2
    except ValueError as exc:  # pydantic's ValidationError is a ValueError
        print(str(exc).replace("\n", " ")[:500], file=sys.stderr)
        return 2
    except MemoryError:
        print("MemoryError: the models need more memory than allowed to compile", file=sys.stderr)
        return 3
    return 0


if __name__ == "__main__":
    sys.exit(main())
