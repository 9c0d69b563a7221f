"""``trainer``: train, evaluate and run the neural renderer. Commands arrive with issue #5."""

import click


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """Train and run the neural material renderer (launch, train, eval, render: not built yet)."""


if __name__ == "__main__":
    main()
