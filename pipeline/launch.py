"""``polyvec``'s console entry point: the keypoints child first, then the CLI (:mod:`pipeline.cli`).

Before this process imports anything of its own it forks the child that an in-process run computes
its keypoints in (:mod:`pipeline.engine.execute.early_child`), and the child imports torch at once, on
the other core, while this process imports the CLI, composes the config and plans the batch (~0.4 s).
The batch adopts it when it has keypoints to compute in this process, and ends it otherwise
(stages/DECISIONS.md, engine).

Standard library only, here and in the module it forks with: the fork is safe while this process has
no threads, and the point is to start before the imports.
"""

from __future__ import annotations

import sys

#: Arguments with which ``polyvec`` runs no drawing: no child for them.
NO_RUN_FLAGS = frozenset({"-h", "--help", "-c", "--cfg", "--info", "--hydra-help", "--version",
                          "--shell-completion", "-sc"})


def main() -> None:
    """Console entry point of ``polyvec`` (see :func:`pipeline.cli.main`); ``polyvec serve …`` is
    :func:`pipeline.serve.main` (a server: no keypoints child forked for it)."""
    if sys.argv[1:2] == ["serve"]:
        from pipeline.serve import main as serve_main

        serve_main(sys.argv[2:])
        return
    if sys.platform == "linux" and not NO_RUN_FLAGS.intersection(sys.argv[1:]):
        from pipeline.engine.execute.early_child import start_early

        start_early()
    from pipeline.cli import main as cli_main

    cli_main()


if __name__ == "__main__":
    main()
