"""``polyvec``'s console entry point: the keypoints child first, then the CLI (:mod:`pipeline.cli`).

The child (:func:`pipeline.child.start_early`) starts before this process imports anything of its
own, so that torch's import runs on the other core while this one imports the CLI (~0.3 s), composes
the config and plans the batch; a run that has nothing for it ends it (stages/DECISIONS.md, engine).
"""

from __future__ import annotations

import sys

#: Flags with which ``polyvec`` runs no drawing: no child for them.
NO_RUN_FLAGS = frozenset({"-h", "--help", "-c", "--cfg", "--info", "--hydra-help", "--version",
                          "--shell-completion", "-sc"})


def main() -> None:
    """Console entry point of ``polyvec`` (see :func:`pipeline.cli.main`)."""
    if not NO_RUN_FLAGS.intersection(sys.argv[1:]):
        from pipeline.child import start_early

        start_early()
    from pipeline.cli import main as cli_main

    cli_main()


if __name__ == "__main__":
    main()
