"""``capvector inspect DIR``: a capability vector's norms (and cosines) by layer, as a table and a
plot (``capvector.vectors.inspect``), the plot also shown in a Lightning logger when one is given.
Its entry point is here, not in ``vectors/``, which never imports Lightning."""

from __future__ import annotations

from lightning.pytorch.loggers import Logger

from capvector.tool_cli import Tool
from capvector.training.loggers import log_figure


def main(argv: list[str] | None = None) -> int:
    """Its options are ``inspect_vector``'s parameters, and ``--logger``."""
    from capvector.vectors.inspect import inspect_vector

    tool = Tool(inspect_vector, "inspect", skip=["progress"])
    tool.parser.add_argument(
        "--logger", type=Logger | None, default=None,
        help="a Lightning logger to show the --plot in as well, given as in a fit config's "
        "trainer.logger (TensorBoard, W&B and MLflow show it)",
    )  # fmt: skip
    options = tool.parse(argv)
    logger = options.pop("logger")
    report = tool.call(options, progress=True)
    print(report.table())
    print(
        f"\n{report.num_tensors} tensors ({report.lowrank_tensors} low-rank), ‖c‖ = {report.norm:.4g}"
    )
    if against := options["against"]:
        cosine = "undefined (a zero vector)" if report.cosine is None else f"{report.cosine:.4f}"
        print(
            f"cosine with {against}: {cosine} over {report.shared_tensors} shared "
            f"tensors ({len(report.only_here)} only here, {len(report.only_against)} only there)"
        )
    if options["plot"]:
        print(f"plot: {options['plot']}")
        if logger is not None:
            log_figure([logger], "inspect/norms_by_layer", options["plot"])
            logger.finalize("success")
    return 0
