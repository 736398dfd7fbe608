"""The docs hold together: every relative link and image points to a file that exists (and a heading
that exists, for links with #anchors), and the README stays a landing page."""

import glob
import os
import re

import pytest

from conftest import REPO

PAGES = sorted(
    [
        os.path.join(REPO, "README.md"),
        os.path.join(REPO, "results", "README.md"),
        *glob.glob(os.path.join(REPO, "docs", "*.md")),
    ]
)
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped (not - and _), spaces as -."""
    return re.sub(r"[^a-z0-9 _-]", "", heading.strip().lower()).replace(" ", "-")


def anchors(path: str) -> set:
    text = FENCE.sub("", open(path).read())
    return {slug(line.lstrip("#")) for line in text.splitlines() if line.startswith("#")}


def links(path: str) -> list:
    text = FENCE.sub("", open(path).read())  # links inside code blocks are not links
    return [target for target in LINK.findall(text) if not re.match(r"[a-z]+:", target)]


def test_slug_follows_githubs_rules():
    assert slug("Does `--bf16` change learning?") == "does---bf16-change-learning"
    assert slug("MKL on AMD CPUs: `tools/mkl_avx512.sh`") == "mkl-on-amd-cpus-toolsmkl_avx512sh"
    assert slug("Ablation (paper Section 5.4)") == "ablation-paper-section-54"


def test_the_pages_link_somewhere():
    assert len(PAGES) >= 9 and sum(len(links(page)) for page in PAGES) > 30


@pytest.mark.parametrize("page", PAGES, ids=lambda p: os.path.relpath(p, REPO))
def test_every_relative_link_points_to_something_that_exists(page):
    broken = []
    for target in links(page):
        path, _, anchor = target.partition("#")
        resolved = os.path.normpath(os.path.join(os.path.dirname(page), path)) if path else page
        if not os.path.exists(resolved):
            broken.append(f"{target}: no {os.path.relpath(resolved, REPO)}")
        elif anchor and resolved.endswith(".md") and anchor not in anchors(resolved):
            broken.append(f"{target}: no heading #{anchor} in {os.path.relpath(resolved, REPO)}")
    assert not broken, "\n".join(broken)


def test_readme_is_a_landing_page():
    # the README holds what this is, how to run it, OPARL in one page and the headline result; details live in docs/
    assert len(open(os.path.join(REPO, "README.md")).read()) <= 12000
