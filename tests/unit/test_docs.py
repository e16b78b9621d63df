"""The documentation: the site builds with ``mkdocs build --strict`` (mkdocs.yml turns a link to a missing page or
anchor, or a page left out of the nav, into a warning, and --strict into a failure), README.md stays a front door
of at most 15 KB, every page of docs/ stays under 40 KB, and every link of README.md resolves: README.md lies
outside mkdocs' docs_dir, so mkdocs does not check it, and this test does (files, and anchors as both GitHub and
the built site name them)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import unicodedata
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
README = REPO / "README.md"
DOCS = REPO / "docs"
README_LIMIT = 15 * 1024
PAGE_LIMIT = 40 * 1024
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def build_site(config: Path, site: Path) -> subprocess.CompletedProcess:
    """``mkdocs build --strict`` of ``config`` into ``site``, in a clean environment."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("FLEETSLAM_")}
    env["NO_MKDOCS_2_WARNING"] = "1"  # mkdocs-material's notice about mkdocs 2, not a warning about these docs
    return subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file", str(config),
                           "--site-dir", str(site)], cwd=config.parent, capture_output=True, text=True, timeout=300,
                          env=env)


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    result = build_site(REPO / "mkdocs.yml", out)
    assert "No module named mkdocs" not in result.stderr, "mkdocs is missing: pip install -e '.[dev]'"
    assert result.returncode == 0, result.stdout + result.stderr
    return out


def without_code(text: str) -> str:
    """Markdown without fenced code blocks and inline code spans (no links or headings live there)."""
    text = re.sub(r"^(```|~~~).*?^\1[ \t]*$", "", text, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def github_anchor(heading: str) -> str:
    """The anchor GitHub gives a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"`|\*\*|\*|_(?=\w)|(?<=\w)_|\[([^\]]*)\]\([^)]*\)", lambda m: m.group(1) or "", heading)
    text = unicodedata.normalize("NFC", text.strip().lower())
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def headings(path: Path) -> list[str]:
    return [m.group(2) for m in re.finditer(r"^(#{1,6})\s+(.+?)\s*#*\s*$", without_code(path.read_text()), re.M)]


def site_page(site: Path, page: Path) -> Path:
    """The built HTML of a docs page (mkdocs' directory URLs: docs/x.md -> site/x/index.html)."""
    relative = page.relative_to(DOCS).with_suffix("")
    return site / "index.html" if relative.name == "index" else site / relative / "index.html"


def link_problems(markdown: str, base: Path, site: Path) -> list[str]:
    """Every relative link of ``markdown`` (a file in ``base``) that does not resolve: a missing file, or an anchor
    that the target's headings (as GitHub names them) or its built page (for docs/ pages) do not hold."""
    problems = []
    for target in LINK.findall(without_code(markdown)):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # https:, mailto:
            continue
        path_text, _, anchor = target.partition("#")
        path = (base / path_text).resolve() if path_text else README
        if not path.exists():
            problems.append(f"{target}: no file {path_text}")
            continue
        if not anchor:
            continue
        if path.suffix != ".md":
            problems.append(f"{target}: an anchor into a file that is not Markdown")
            continue
        if anchor not in {github_anchor(h) for h in headings(path)}:
            problems.append(f"{target}: {path.name} has no heading with the anchor #{anchor}")
        if path.is_relative_to(DOCS):
            html = site_page(site, path)
            if not html.exists() or f'id="{anchor}"' not in html.read_text():
                problems.append(f"{target}: the built page {html.relative_to(site)} has no id {anchor}")
    return problems


def test_the_site_builds_strictly_with_every_page(site):
    for page in DOCS.glob("*.md"):
        assert site_page(site, page).exists(), page.name
    assert (site / "figures" / "rerun_mrclam.png").exists()


def test_the_readme_is_at_most_15_kb():
    size = README.stat().st_size
    assert size <= README_LIMIT, f"README.md is {size} bytes; move detail into docs/"


@pytest.mark.parametrize("page", sorted(p.name for p in DOCS.glob("*.md")))
def test_every_docs_page_is_under_40_kb(page):
    size = (DOCS / page).stat().st_size
    assert size < PAGE_LIMIT, f"docs/{page} is {size} bytes; split it by topic"


def test_every_readme_link_resolves(site):
    text = README.read_text()
    assert link_problems(text, REPO, site) == []
    links = LINK.findall(without_code(text))
    assert sum(link.startswith("docs/") and ".md" in link for link in links) >= 8, links
    assert "docs/results.md" in links, "the README's first screen names the results table"


def test_the_readme_first_screen_has_the_two_commands_a_real_data_run_and_the_results():
    first_screen = README.read_text().split("\n## ", 3)
    head = "\n## ".join(first_screen[:3])  # the title, the introduction and the next two sections
    for text in ("make demo", "make test", "fleetslam run --dataset mrclam:", "docs/results.md"):
        assert text in head, text


def test_a_broken_link_or_anchor_is_caught(site, tmp_path):
    assert link_problems("[x](docs/nowhere.md)", REPO, site) == ["docs/nowhere.md: no file docs/nowhere.md"]
    problems = link_problems("[x](docs/results.md#no-such-heading) [y](#nor-here)", REPO, site)
    assert len(problems) == 3 and all("no-such-heading" in p or "nor-here" in p for p in problems), problems
    assert link_problems("`[x](docs/nowhere.md)` and [y](https://zenoh.io)", REPO, site) == []
    # mkdocs --strict fails on the same mistake inside docs/
    shutil.copytree(DOCS, tmp_path / "docs")
    shutil.copy(REPO / "mkdocs.yml", tmp_path / "mkdocs.yml")
    with open(tmp_path / "docs" / "data.md", "a") as page:
        page.write("\nSee [the results](results.md#no-such-heading).\n")
    result = build_site(tmp_path / "mkdocs.yml", tmp_path / "site")
    assert result.returncode != 0 and "no-such-heading" in result.stdout + result.stderr


def test_github_anchors_are_named_as_github_names_them():
    assert github_anchor("Offline runs on real data") == "offline-runs-on-real-data"
    assert github_anchor("Operations: crash safety, hostile input (issues 14, 15, 16)") == \
        "operations-crash-safety-hostile-input-issues-14-15-16"
    assert github_anchor("The `fleetslam run` command") == "the-fleetslam-run-command"
