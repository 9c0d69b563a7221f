"""``shards``: inspect shard stores. Its commands arrive with the store (issue #3)."""

import click


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """Inspect shaderball shard stores (ls, info, verify, show, export: not built yet)."""


if __name__ == "__main__":
    main()
