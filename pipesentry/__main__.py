from pipesentry.cli import app

app(prog_name="pipesentry")
