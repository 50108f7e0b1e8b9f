"""Issue 63, history out of the product: the README stays short, every default keeps a one-line reason with a link,
``scripts/`` holds only the tools that are listed, every study is in the ``experiments/`` index, and no link points
at a file that is not there (the notes and study scripts that moved to ``experiments/`` above all)."""
import re
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
LINK = re.compile(r"\]\(([^)\s]+)\)")
# A repository path written out in prose or a comment, under scripts, experiments or docs (a glob is skipped).
PATH = re.compile(r"(?<![\w./-])((?:scripts|experiments|docs)/[\w./*-]*[\w*])")


def _slug(heading: str) -> str:
    """GitHub's anchor of a markdown heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(md: Path) -> set:
    return {_slug(m) for m in re.findall(r"^#+ (.+)$", md.read_text(), re.M)}


def _leaf_lines(text: str):
    """(line number, indent, key, value, comment) of every key of a YAML file's block mappings."""
    for n, line in enumerate(text.splitlines(), 1):
        m = re.match(r"^( *)([\w]+):(.*)$", line)
        if m:
            value, _, comment = m.group(3).partition("#")
            yield n, len(m.group(1)), m.group(2), value.strip(), comment.strip()


def test_readme_is_short_and_keeps_set_up_use_and_numbers():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 250
    for heading in ("## Set up", "## Use", "## Numbers"):
        assert f"\n{heading}\n" in text, heading


def test_every_default_has_a_reason_and_a_link_that_resolves():
    path = ROOT / "configs" / "default.yaml"
    text = path.read_text()
    assert len(text.splitlines()) <= 150
    rows = list(_leaf_lines(text))
    chain = []  # (indent, comment) of the keys enclosing the current one
    for n, indent, key, value, comment in rows:
        chain = [c for c in chain if c[0] < indent]
        if value:  # a key with a value (not a section): its own reason, one line
            assert comment, f"default.yaml line {n}: {key} has no comment saying why"
            linked = [c for _, c in chain] + [comment]
            assert any(re.search(r"(docs|experiments)/", c) for c in linked), \
                f"default.yaml line {n}: neither {key} nor its sections link to docs/ or experiments/"
        chain.append((indent, comment))
    for target in re.findall(r"((?:docs|experiments)/[\w./-]+\.md)(#[\w-]+)?", text):
        doc, anchor = target
        assert (ROOT / doc).is_file(), f"default.yaml links to {doc}, which does not exist"
        if anchor:
            assert anchor[1:] in _anchors(ROOT / doc), f"default.yaml links to {doc}{anchor}: no such section"


def test_docs_config_names_every_key():
    text = (ROOT / "docs" / "config.md").read_text()

    def keys(d, prefix=""):  # the keys that hold values; a section is a heading there
        for k, v in d.items():
            if isinstance(v, dict) and v:
                yield from keys(v, prefix + k + ".")
            else:
                yield prefix + k

    named = set(re.findall(r"`([\w.]+)`", text))
    missing = [k for k in keys(yaml.safe_load((ROOT / "configs" / "default.yaml").read_text()))
               if not any(k == n or k.startswith(n + ".") for n in named)]  # an inline mapping counts for its keys
    assert not missing, f"docs/config.md does not explain {missing}"


def test_scripts_holds_at_most_eight_tools_all_listed():
    tools = sorted(p.name for p in (ROOT / "scripts").iterdir() if p.is_file() and p.name != "README.md")
    listed = (ROOT / "scripts" / "README.md").read_text()
    assert len(tools) <= 8, tools
    assert [t for t in tools if f"| `{t}` |" not in listed] == []


def test_the_experiments_index_has_every_study():
    index = (ROOT / "experiments" / "README.md").read_text()
    linked = {(ROOT / "experiments" / t.split("#")[0]).resolve() for t in LINK.findall(index)}
    studies = [p for p in (ROOT / "experiments").glob("*.py")] + list((ROOT / "experiments" / "notes").glob("*.md"))
    assert studies and [p.name for p in studies if p.resolve() not in linked] == []
    assert not (ROOT / "docs" / "experiments").exists()


def test_links_and_paths_point_at_files_that_exist():
    bad = []
    docs = [ROOT / "README.md", ROOT / "scripts" / "README.md", ROOT / "experiments" / "README.md",
            *sorted((ROOT / "docs").glob("*.md")), *sorted((ROOT / "experiments" / "notes").glob("*.md"))]
    for md in docs:
        for target in LINK.findall(md.read_text()):
            file = target.split("#")[0]
            if file and not file.startswith(("http:", "https:", "mailto:")) and not (md.parent / file).exists():
                bad.append(f"{md.relative_to(ROOT)} links to {target}")
    # Paths in prose and comments of the product (the notes keep their commands as they were run).
    product = [ROOT / "README.md", ROOT / "scripts" / "README.md", *sorted((ROOT / "docs").glob("*.md")),
               *sorted((ROOT / "configs").rglob("*.yaml")), *sorted((ROOT / "retinexgs").rglob("*.py")),
               *sorted((ROOT / "tests").glob("*.py")), *sorted((ROOT / "scripts").glob("*.py"))]
    for f in product:
        for path in PATH.findall(f.read_text()):
            if "*" not in path and not (ROOT / path).exists():
                bad.append(f"{f.relative_to(ROOT)} names {path}")
    assert bad == []
