"""``python -m mocknode``: the same as ``pipesentry mock-node``."""
import typer

from mocknode.cli import mock_node

if __name__ == "__main__":
    typer.run(mock_node)
