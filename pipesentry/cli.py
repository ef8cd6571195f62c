"""The ``pipesentry`` command: one subcommand per job, each implemented in pipesentry/commands/
(the mock node's in mocknode/cli.py). A command imports what it runs inside its function, so
building the command line (``pipesentry --help``) imports no numpy, scipy or SQLAlchemy.
"""
from __future__ import annotations

import typer

from mocknode.cli import mock_node
from pipesentry.commands.alerts import alerts_app
from pipesentry.commands.analyze import analyze
from pipesentry.commands.api import api
from pipesentry.commands.apikey import apikey_app
from pipesentry.commands.demo import demo
from pipesentry.commands.gateway import gateway
from pipesentry.commands.node_check import node_check

app = typer.Typer(
    help="PipeSentry: permanent guided-wave pipe monitoring.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    # Plain click help: it wraps at the terminal's width; rich's boxed tables truncated option names at 80 columns.
    rich_markup_mode=None,
)


@app.callback()
def _root() -> None:
    """PipeSentry: permanent guided-wave pipe monitoring (mock nodes, gateway, API, analysis)."""


app.command()(analyze)
app.command()(demo)
app.command()(gateway)
app.command()(api)
app.command("node-check")(node_check)
app.add_typer(apikey_app, name="apikey")
app.add_typer(alerts_app, name="alerts")
app.command("mock-node")(mock_node)
