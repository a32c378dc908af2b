"""mkdocs hook: the README becomes the home page and formulations/ a section, read from where
they live in the repository (no copies to keep in step), with the result pictures (the
notebooks come in through the symbolic link docs/notebooks, for mkdocs-jupyter to see them); their
repository-relative links are rewritten to the site's pages."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parents[1]
PICTURES = "results-files/"


def _site_links(text: str, prefix: str) -> str:
    """Links written relative to the repository root (README) -> the site's pages, pictures and
    the repository for anything else."""
    text = text.replace("](docs/", "](" + prefix).replace("](benchmarks/results/", "](" + prefix + PICTURES)
    return re.sub(r"\]\((?!https?:|#|formulations/|results-files/|[a-z_-]+\.md)([^)]*/[^)]*)\)",
                  lambda m: f"](https://github.com/fiberplan/fiberplan/blob/main/{m.group(1)})", text)


def on_files(files: Files, config: Any) -> Files:
    files.append(File.generated(config, "index.md", content=_site_links((ROOT / "README.md").read_text(), "")))
    for path in sorted((ROOT / "formulations").glob("*.md")):
        text = path.read_text().replace("](../docs/", "](../")
        files.append(File.generated(config, f"formulations/{path.name}", content=text))
    for picture in sorted((ROOT / "benchmarks" / "results").glob("*.png")):
        files.append(File.generated(config, PICTURES + picture.name, abs_src_path=str(picture)))
    return files


def on_page_markdown(markdown: str, page: Any, config: Any, files: Files) -> str:
    """docs/*.md link to ../formulations and ../benchmarks/results as the repository lays them out."""
    if page.file.src_uri in ("results.md", "mpc-history.md"):
        return markdown.replace("](../formulations/", "](formulations/").replace("](../benchmarks/results/", "](" + PICTURES)
    return markdown
