"""The ``pipesentry`` command: one subcommand per job, each implemented in pipesentry/commands/."""
from __future__ import annotations

import typer

from pipesentry.commands.alerts import alerts_app
from pipesentry.commands.analyze import analyze
from pipesentry.commands.api import api
from pipesentry.commands.apikey import apikey_app
from pipesentry.commands.demo import demo
from pipesentry.commands.gateway import gateway

app = typer.Typer(
    help="PipeSentry: permanent guided-wave pipe monitoring.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root() -> None:
    """PipeSentry: permanent guided-wave pipe monitoring (mock nodes, gateway, API, analysis)."""


app.command()(analyze)
app.command()(demo)
app.command()(gateway)
app.command()(api)
app.add_typer(apikey_app, name="apikey")
app.add_typer(alerts_app, name="alerts")

try:  # the mock node registers itself once its package is in place
    from mocknode.cli import mock_node
except ImportError:  # pragma: no cover - only while the mock node is being built
    pass
else:
    app.command("mock-node")(mock_node)
