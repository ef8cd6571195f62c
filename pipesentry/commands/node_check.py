"""`pipesentry node-check URL`: docs/protocol.md's numbered requirements run against a node."""
from __future__ import annotations

from typing import Annotated

import typer

from pipesentry.errors import fail


def node_check(
    url: Annotated[str, typer.Argument(help="pyserial URL of the node: /dev/ttyUSB0, socket://host:port, ...")],
    baud: Annotated[int, typer.Option(min=300, help="line rate, bit/s (8N1)")] = 230400,
    timeout_s: Annotated[float, typer.Option(min=0.01, max=60.0, help="reply timeout per command, s")] = 1.0,
    retries: Annotated[int, typer.Option(min=0, max=20, help="resends after a timeout or BUSY")] = 3,
    shot_period_s: Annotated[float, typer.Option(min=0.0, max=10.0, help="ACQUIRE time per averaged shot, s")] = 0.01,
    compute_timeout_s: Annotated[float, typer.Option(min=0.1, max=86400.0, help="COMPUTE_DI timeout, s")] = 60.0,
    reboot_command: Annotated[str | None, typer.Option(
        help="a command that power-cycles the node (R-BOOT-2/3; without it they are n/a)")] = None,
    reboot_wait_s: Annotated[float, typer.Option(min=0.1, max=600.0, help="how long a reboot may take, s")] = 30.0,
) -> None:
    """Check a node against docs/protocol.md: one line per requirement (passed / FAILED with the bytes
    that failed / n/a), exit 0 only when none failed, 1 when one did, 2 when the node cannot be reached."""
    from nodecheck.outcomes import Status, all_passed
    from nodecheck.runner import reboot_by_command, run_checks
    from nodecheck.session import CheckAborted, Timing
    from nodelink.transport import NodeLinkError

    try:
        reboot = None if reboot_command is None else reboot_by_command(reboot_command, timeout_s=reboot_wait_s)
    except ValueError as exc:
        fail(str(exc))
    timing = Timing(timeout_s=timeout_s, retries=retries, shot_period_s=shot_period_s,
                    compute_timeout_s=compute_timeout_s)
    try:
        outcomes = run_checks(url, timing, reboot=reboot, reboot_wait_s=reboot_wait_s, baudrate=baud)
    except CheckAborted as exc:
        fail(str(exc))
    except NodeLinkError as exc:  # the port cannot be opened, or vanished under the checks
        fail(str(exc).splitlines()[0])
    for outcome in outcomes:
        typer.echo(outcome.line())
    counts = {status: sum(o.status == status for o in outcomes) for status in Status}
    typer.echo(f"{counts[Status.PASSED]} passed, {counts[Status.FAILED]} failed, "
               f"{counts[Status.NOT_APPLICABLE]} not applicable")
    raise typer.Exit(0 if all_passed(outcomes) else 1)
