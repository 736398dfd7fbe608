"""The docs hold together: every relative link and image points to a file that exists (and a heading
that exists, for links with #anchors), every command in a ```bash block names a file and flags that exist,
and the README's headline numbers are those of the committed results."""

import ast
import glob
import os
import re
import shlex

import pytest

from conftest import REPO

PAGES = sorted(
    [
        os.path.join(REPO, "README.md"),
        os.path.join(REPO, "results", "README.md"),
        *glob.glob(os.path.join(REPO, "docs", "*.md")),
        *glob.glob(os.path.join(REPO, "results", "**", "README.md"), recursive=True),
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


BASH = re.compile(r"^```bash\n(.*?)^```", re.S | re.M)
WRAPPERS = {"nice", "setsid", "nohup", "time", "/usr/bin/time"}  # each runs the command that follows it


def commands(path: str) -> list:
    """Each command of the page's ```bash blocks as its words: continued lines joined, comments dropped, split at
    &&, ||, ;, | and $( ); environment assignments and wrappers taken off."""
    found = []
    for block in BASH.findall(open(path).read()):
        if "git checkout" in block or "git worktree add" in block:
            continue  # commands of another commit's checkout
        for line in block.replace("\\\n", " ").splitlines():
            try:
                words = shlex.split(line, comments=True)
            except ValueError:  # an unbalanced quote: not a command this test can read
                continue
            command = []
            for word in [*words, "&&"]:
                if word in {"&&", "||", ";", "|", "&"} or word.startswith("$("):
                    found.append(command)
                    command = []
                else:
                    command.append(word.rstrip(")"))
    return [unwrap(words) for words in found if words]


def unwrap(words: list) -> list:
    """A command without its environment assignments and wrappers (nice -n N, tools/mkl_avx512.sh, ...)."""
    while words:
        if re.match(r"[A-Z_]+=", words[0]) or words[0] in WRAPPERS:
            words = words[1:]
        elif words[0] == "-n":  # nice's niceness
            words = words[2:]
        elif words[:2] == ["bash", "tools/mkl_avx512.sh"]:
            words = words[2:]
        else:
            break
    return words


def script_flags(path: str) -> set:
    """The flags of a script's tyro Args (a bool field also as --no-...), or of a tool's argparse parser and a shell
    script's case patterns, read from its source."""
    source = open(path).read()
    if path.endswith("_continuous_action.py"):
        args = next(n for n in ast.parse(source).body if isinstance(n, ast.ClassDef) and n.name == "Args")
        fields = [(n.target.id, ast.unparse(n.annotation)) for n in args.body if isinstance(n, ast.AnnAssign)]
        flags = {"--" + name.replace("_", "-") for name, _ in fields}
        return flags | {"--no-" + name.replace("_", "-") for name, kind in fields if kind == "bool"} | {"--help"}
    return set(re.findall(r"(--[a-z0-9][a-z0-9-]*)", source)) | {"--help"}


def unknown_in(words: list, created: frozenset = frozenset()) -> list:
    """What a command names that does not exist: its python or bash file (unless the page `cp`s it into being, as
    forking.md does), or a flag that file does not take."""
    if len(words) < 2 or words[0] not in {"python", "python3", "bash"} or words[1] in {"-m", "-c"}:
        return []
    target = words[1]
    if not target.endswith((".py", ".sh")) or target.startswith(("/", "$", "..", "~")):
        return []  # a file outside the repository (the authors' release, a scratch script)
    path = os.path.join(REPO, target)
    if not os.path.exists(path):
        return [] if target in created else [f"no file {target}"]
    known = script_flags(path)
    if len(words) > 2 and os.path.exists(os.path.join(REPO, f"{words[2]}_continuous_action.py")):
        known = known | script_flags(os.path.join(REPO, f"{words[2]}_continuous_action.py"))  # a tool that runs a script
    own, passed_on = (words[2:], []) if "--" not in words else (words[2 : words.index("--")], words[words.index("--") + 1 :])
    wrong = [f"{target} takes no {w.split('=')[0]}" for w in own if w.startswith("--") and w.split("=")[0] not in known]
    if passed_on:  # benchmark.sh passes what follows -- to every script it runs
        every = set().union(*(script_flags(s) for s in glob.glob(os.path.join(REPO, "*_continuous_action.py"))))
        wrong += [f"no script takes {w}" for w in passed_on if w.startswith("--") and w.split("=")[0] not in every]
    return wrong


def test_the_command_check_finds_a_missing_file_and_an_unknown_flag():
    assert unwrap(["nice", "-n", "10", "bash", "tools/mkl_avx512.sh", "python", "x.py"]) == ["python", "x.py"]
    assert unknown_in(["python", "td3_continuous_action.py", "--env-id", "Hopper-v4", "--no-cuda"]) == []
    assert unknown_in(["python", "td3_continuous_action.py", "--env", "Hopper-v4"]) == [
        "td3_continuous_action.py takes no --env"
    ]
    assert unknown_in(["python", "tools/welch.py", "--paired"]) == []
    assert unknown_in(["python", "tools/welsh.py"]) == ["no file tools/welsh.py"]
    assert unknown_in(["python", "ddpg_continuous_action.py"], created=frozenset({"ddpg_continuous_action.py"})) == []
    assert unknown_in(["python", "tools/speed/phase_times.py", "sac", "--csv", "x", "--eval-episodes", "1"]) == []
    assert unknown_in(["bash", "benchmark.sh", "--algos", "td3", "--", "--eval-frequency", "1", "--evl"]) == [
        "no script takes --evl"
    ]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: os.path.relpath(p, REPO))
def test_every_command_names_a_file_and_flags_that_exist(page):
    created = frozenset(words[-1] for words in commands(page) if words[:1] == ["cp"])
    wrong = [f"{' '.join(words)}: {problem}" for words in commands(page) for problem in unknown_in(words, created)]
    assert not wrong, "\n".join(wrong)


def table_rows(text: str) -> list:
    """A markdown page's table rows, each as its cells."""
    return [[c.strip() for c in line.strip().strip("|").split("|")] for line in text.splitlines() if line.startswith("|")]


def test_the_readmes_results_are_the_committed_tables():
    """The README's headline (IQM and P(OPARL > X) with their intervals) and its per-task table carry the numbers of
    results/main/table.md, which plot_results.py regenerates from the committed CSV."""
    readme = open(os.path.join(REPO, "README.md")).read()
    committed = table_rows(open(os.path.join(REPO, "results", "main", "table.md")).read())
    iqm = {row[0]: f"{row[1]} {row[2]}" for row in committed if len(row) == 11 and row[0] in {"oparl", "td3", "sac"}}
    probability = {row[1]: (float(row[2]), row[3]) for row in committed if len(row) == 4 and row[0] == "oparl"}
    assert len(iqm) == 3 and set(probability) == {"td3", "sac"}
    for algo, text in iqm.items():
        assert text in readme, f"the README lacks {algo}'s IQM {text}"
    for other, (p, ci) in probability.items():
        low, high = (float(v) for v in ci.strip("[]").split(", "))
        assert f"{p:.2f} [{low:.2f}, {high:.2f}]" in readme, (
            f"the README lacks P(OPARL > {other}) {p:.2f} [{low:.2f}, {high:.2f}]"
        )
    ours = {row[0]: [c.replace("**", "") for c in row[1:4]] for row in table_rows(readme)}
    checked = 0
    for row in committed:
        task = row[0].removesuffix("-v0")
        if row[0].endswith("-v0") and task in ours and " +- " in row[1]:  # a per-task row: oparl, sac, td3
            assert ours[task] == [re.sub(r" \(\d+\)$", "", c.replace("**", "")) for c in row[1:4]], task
            checked += 1
    assert checked == 18, f"the README's per-task table has {checked} of the 18 DMC tasks"
