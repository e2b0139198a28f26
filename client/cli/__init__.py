"""The `posecast` command line: the parser and one small module per command, each
parsing and calling library code (thin on purpose, so that tests call the same
functions).

- ``parser``: every command, option and help text; it imports only constants, so that
  ``--version`` and ``--help`` answer at once.
- ``run``: ``main``, logging, the config file, and the dispatch to the commands.
- a module per command or family: ``serve`` (and ``token``), ``play``, ``view``,
  ``demo``, ``eval``, ``crossval``, ``crossval_body``, ``record`` (and ``replay``),
  ``export``, ``vmc``; benches are dispatched to ``client.bench``.
- what they share: ``arguments`` (argument types), ``config_file`` (``--config``),
  ``console`` (status lines and summaries), ``common`` (one-line failures).

May import every other client package; nothing imports cli.
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from typing import Any

# names tests and tools read from here, found in the module that holds them, on first use
_FROM = {"_parser": "parser", "_HOSTILE_ATTACKS": "parser", "_FANOUT_BUDGET_MS": "parser",
         "_with_config": "run", "_eval_flags_given": "run"}


def main(argv: Sequence[str] | None = None) -> int:
    """`posecast ARGS...` (the console script); the exit status."""
    from posecast.client.cli.run import main as run

    return run(argv)


def __getattr__(name: str) -> Any:
    module = _FROM.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)
