"""docs/layout.md matches the tree: every module of the packages is named there, and every file or folder it
names exists."""
from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
LAYOUT = REPO / "docs" / "layout.md"
PACKAGES = ("lcpr_common", "lcpr_core", "lcpr_offline", "lcpr_ros", "vseq2pc_ros", "backend_ros", "ros_common",
            "msg_tools", "citysim")
#: a path-like word of the page: folder/ or name.py, possibly with folders before it
PATH_WORD = re.compile(r"(?<![\w./-])((?:[A-Za-z_][\w-]*/)*(?:[A-Za-z_][\w-]*\.py|[A-Za-z_][\w-]*/))(?![\w.-])")


def layout_text() -> str:
    return LAYOUT.read_text(encoding="utf-8")


def sections(text: str) -> dict[str, str]:
    """The tree block's text under each top-level folder (a line starting with ``name/`` at column 0)."""
    block = re.search(r"^```\n(.*?)^```", text, re.MULTILINE | re.DOTALL)
    assert block, "docs/layout.md has no tree block"
    found: dict[str, str] = {}
    current = ""
    for line in block.group(1).splitlines():
        top = re.match(r"([A-Za-z_][\w-]*)/", line)
        if top:
            current = top.group(1)
        found[current] = found.get(current, "") + line + "\n"
    return found


def modules() -> list[Path]:
    """Every Python module of the project's packages, relative to the repository (package markers left out)."""
    found = []
    for package in PACKAGES:
        found += [p.relative_to(REPO) for p in (REPO / package).rglob("*.py") if p.name != "__init__.py"]
    return sorted(found)


def named_paths(text: str) -> set[str]:
    return {m.group(1) for m in PATH_WORD.finditer(text)}


def test_every_module_of_the_packages_is_named_under_its_package_on_the_layout_page() -> None:
    by_package = {name: set(re.findall(r"[\w-]+", text)) for name, text in sections(layout_text()).items()}
    missing = [str(m) for m in modules() if m.stem not in by_package.get(m.parts[0], set())]
    assert not missing, f"docs/layout.md does not name these modules under their package: {missing}"


def test_every_file_and_folder_the_layout_page_names_exists() -> None:
    tree = {str(p.relative_to(REPO)) + ("/" if p.is_dir() else "")
            for p in REPO.rglob("*") if ".venv" not in p.parts and ".git" not in p.parts}
    missing = []
    for name in named_paths(layout_text()):
        if not any(path == name or path.endswith("/" + name) for path in tree):
            missing.append(name)
    assert not missing, f"docs/layout.md names files or folders that do not exist: {sorted(missing)}"


def test_the_layout_check_sees_a_stale_name() -> None:
    assert "lcpr/evaluate.py" in named_paths("  lcpr/evaluate.py    a bag through LoopDetector")
    assert "evaluation.py" in named_paths("evaluation.py  ground truth")
    assert "scan_folder.py" in named_paths("(convert/scan_folder.py)") or "convert/scan_folder.py" in named_paths(
        "(convert/scan_folder.py)")
