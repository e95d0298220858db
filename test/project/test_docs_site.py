"""The documentation: the generated parameter pages are current, the README's links resolve, CI runs the
README's test command. (`mkdocs build --strict`, in that command, checks the site's own links.)"""
from __future__ import annotations

import importlib
import re
from pathlib import Path
from urllib.parse import unquote

import pytest

REPO = Path(__file__).resolve().parents[2]
README = REPO / "README.md"

#: module whose markdown_text() writes the page -> the page
PARAMETER_PAGES = {
    "lcpr_ros.params": "docs/reference/lcpr_node_parameters.md",
    "vseq2pc_ros.params": "docs/reference/vseq2pc_node_parameters.md",
    "backend_ros.config": "docs/reference/lcpr_backend_parameters.md",
}
INLINE_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
REFERENCE_LINK = re.compile(r"^\s*\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+\"[^\"]*\")?\s*$", re.MULTILINE)
HTML_SOURCE = re.compile(r"<(?:img|a)\s[^>]*(?:src|href)=\"([^\"]+)\"", re.IGNORECASE)
FENCE = re.compile(r"^```.*?^```", re.MULTILINE | re.DOTALL)


def regenerate_command(module: str, page: str) -> str:
    return f".venv/bin/python -c \"from {module} import markdown_text; print(markdown_text(), end='')\" > {page}"


def relative_targets(markdown: str) -> list[str]:
    """Every link and image target of a Markdown text that points into the repository (code blocks left out)."""
    text = FENCE.sub("", markdown)
    text = re.sub(r"`[^`\n]*`", "", text)  # code spans
    found = INLINE_LINK.findall(text) + REFERENCE_LINK.findall(text) + HTML_SOURCE.findall(text)
    return [t for t in found if not re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", t) and not t.startswith("#")]


def readme_commands() -> list[str]:
    """The commands of the README's first code block, without their comments."""
    block = re.search(r"^```bash\n(.*?)^```", README.read_text(), re.MULTILINE | re.DOTALL)
    assert block, "README.md has no ```bash block"
    lines = [line.split("  #", 1)[0].strip() for line in block.group(1).splitlines() if line.strip()]
    assert len(lines) >= 2, f"README.md's first code block should hold the demo and the test commands: {lines}"
    return lines


def readme_test_command() -> str:
    return readme_commands()[1]


@pytest.mark.parametrize("module", sorted(PARAMETER_PAGES))
def test_the_parameter_pages_match_the_config_dataclasses(module: str) -> None:
    page = PARAMETER_PAGES[module]
    expected = importlib.import_module(module).markdown_text()
    path = REPO / page
    assert path.is_file(), f"{page} is missing; write it with\n  {regenerate_command(module, page)}"
    assert path.read_text() == expected, (
        f"{page} differs from the config dataclasses it documents; regenerate it with\n"
        f"  {regenerate_command(module, page)}")


def test_a_parameter_table_cell_keeps_its_text_and_its_column() -> None:
    from lcpr_common.params import ParamSpec
    from ros_common.params import Leaf, to_markdown

    doc = ParamSpec("a|b <c> [d] *e* under_score", 0, 2147483647, dynamic=True)
    leaf = Leaf(name="group.name", owner="X", kind=int, array=False, default=3, doc=doc)
    top = Leaf(name="plain", owner="X", kind=str, array=True, default=("x", "y"),
               doc=ParamSpec("p", choices=("x", "y")))
    text = to_markdown([leaf, top])
    row = next(line for line in text.splitlines() if line.startswith("| `group.name`"))
    assert row == ("| `group.name` | `3` | int | 0 .. 2147483647 | yes | "
                   "a\\|b &lt;c&gt; \\[d\\] \\*e\\* under\\_score |")
    assert "## `group.*`" in text and "## Top-level parameters" in text
    assert '| `plain` | `["x", "y"]` | str[] | `x`, `y` |  | p |' in text


def test_every_relative_link_and_image_in_the_readme_exists() -> None:
    missing = []
    for target in relative_targets(README.read_text()):
        path = unquote(target.split("#", 1)[0].split("?", 1)[0])
        if path and not (REPO / path).exists():
            missing.append(target)
    assert not missing, f"README.md links to files that do not exist: {missing}"


def test_the_link_finder_sees_links_and_images_and_skips_urls_and_code() -> None:
    text = ("see [the docs](docs/index.md#top) and ![a figure](docs/x.png \"title\")\n"
            "[ref]: docs/ref.md\n<img src=\"docs/y.png\">\n[web](https://example.org) [here](#anchor)\n"
            "`[not](a_link.md)`\n```\n[nor](this.md)\n```\n")
    assert relative_targets(text) == ["docs/index.md#top", "docs/x.png", "docs/ref.md", "docs/y.png"]


def test_ci_runs_exactly_the_test_command_the_readme_gives() -> None:
    run = [line for line in (REPO / ".ci" / "run").read_text().splitlines() if line.strip()]
    assert run[-1].strip() == readme_test_command(), (
        ".ci/run's last line and the README's test command (second line of its first code block) differ")
    assert "mkdocs build --strict" in readme_test_command()


def test_the_readme_is_a_landing_page_of_at_most_200_lines() -> None:
    lines = README.read_text().splitlines()
    assert len(lines) <= 200, f"README.md has {len(lines)} lines; move the depth to a page under docs/"
    assert readme_commands()[0] == "bash scripts/setup.sh && .venv/bin/lcpr_demo"
    assert README.read_text().index("```bash") < 200, "the two commands belong in the README's first lines"


def test_every_figure_in_docs_is_shown_on_a_page() -> None:
    pages = "\n".join(p.read_text() for p in (REPO / "docs").rglob("*.md"))
    shown = {Path(unquote(t)).name for t in relative_targets(pages)}
    unshown = sorted(p.name for p in (REPO / "docs").glob("*.png") if p.name not in shown)
    assert not unshown, f"figures in docs/ that no page shows: {unshown}"
