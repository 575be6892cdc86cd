"""MkDocs hook: the command-line and HTTP reference pages, written from the code at build time.

`reference/cli.md` comes from the `links` argument parser and `reference/http.md` from the app's
OpenAPI document, so neither can say what the code does not; neither is a file in the
repository. They are written by a fresh Python process on every build, so that `mkdocs serve`,
which rebuilds when the package changes (`watch` in mkdocs.yml), shows the code as it is now
rather than as it was first imported.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import reference_cli
import reference_http

#: Where each generated page sits in the site (the nav names these).
CLI_PAGE = "reference/cli.md"
HTTP_PAGE = "reference/http.md"


def cli_parser() -> argparse.ArgumentParser:
    """The `links` command's argument parser."""
    from links_ray.cli.main import build_parser

    return build_parser()


def openapi_document() -> dict[str, Any]:
    """The HTTP app's OpenAPI document, as `GET /openapi.json` serves it: built from the app's
    routes by `serve.http.openapi`, which needs no Ray."""
    from links_ray.serve.http.asgi import api
    from links_ray.serve.http.openapi import openapi_document

    return openapi_document(api.routes)


def pages() -> dict[str, str]:
    """Each generated page's path in the site and its Markdown."""
    return {
        CLI_PAGE: reference_cli.cli_page(cli_parser()),
        HTTP_PAGE: reference_http.http_page(openapi_document()),
    }


def on_files(files: Any, config: Any) -> Any:
    """Add the generated pages to the site's files, refusing a file of the same name in
    docs/, which would be a stale copy."""
    from mkdocs.exceptions import PluginError
    from mkdocs.structure.files import File

    for path in (CLI_PAGE, HTTP_PAGE):
        if files.get_file_from_path(path) is not None:
            raise PluginError(f"docs/{path} is written at build time; remove the file")
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "pages.json"
        done = subprocess.run(
            [sys.executable, __file__, str(out)],
            capture_output=True,
            text=True,
            cwd=Path(config.config_file_path).parent,
            check=False,
        )
        if done.returncode != 0:
            raise PluginError(f"writing the reference pages failed:\n{done.stderr}")
        written = json.loads(out.read_text(encoding="utf-8"))
    for path, markdown in written.items():
        files.append(File.generated(config, path, content=markdown))
    return files


if __name__ == "__main__":  # the hook's fresh process: the pages as JSON into the file named
    Path(sys.argv[1]).write_text(json.dumps(pages()), encoding="utf-8")
