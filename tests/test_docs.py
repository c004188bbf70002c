"""The documentation site (``mkdocs.yml``) builds offline with ``--strict`` from the docstrings and guides."""
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

pytest.importorskip("mkdocs", reason="pip install -e '.[docs]'")
pytest.importorskip("material", reason="pip install -e '.[docs]'")
pytest.importorskip("mkdocstrings_handlers.python", reason="pip install -e '.[docs]'")

ROOT = Path(__file__).resolve().parents[1]
MODULES = sorted(p.stem for p in (ROOT / "sfs_torch").glob("*.py") if not p.stem.startswith("_"))
GUIDES = sorted(p.name for p in (ROOT / "docs").glob("*.md"))


def nav_pages(node):
    if isinstance(node, str):
        yield node
    elif isinstance(node, dict):
        for value in node.values():
            yield from nav_pages(value)
    elif isinstance(node, list):
        for value in node:
            yield from nav_pages(value)


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    out = tmp_path_factory.mktemp("site")
    # no network: any download (web fonts, icons, a social-cards plugin) fails at once, not silently
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1", "HTTP_PROXY": "http://127.0.0.1:9",
           "HTTPS_PROXY": "http://127.0.0.1:9", "http_proxy": "http://127.0.0.1:9",
           "https_proxy": "http://127.0.0.1:9", "NO_PROXY": "", "no_proxy": ""}
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file", str(ROOT / "mkdocs.yml"),
         "--site-dir", str(out)],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=300,
    )
    return out, result


class TestDocs:
    def test_strict_build_succeeds_offline(self, site):
        out, result = site
        assert result.returncode == 0, result.stderr[-4000:]
        assert "WARNING" not in result.stderr, result.stderr[-4000:]
        assert (out / "index.html").is_file() and (out / "search" / "search_index.json").is_file()
        html = "".join(p.read_text(encoding="utf-8") for p in out.rglob("*.html"))
        assert "fonts.googleapis.com" not in html and "fonts.gstatic.com" not in html

    def test_every_module_and_guide_has_a_page_in_the_nav(self, site):
        out, _ = site
        nav = set(nav_pages(yaml.safe_load((ROOT / "mkdocs.yml").read_text(encoding="utf-8"))["nav"]))
        assert set(GUIDES) <= nav, set(GUIDES) - nav
        for module in MODULES:
            page = ROOT / "docs" / "api" / f"{module}.md"
            assert f"::: sfs_torch.{module}" in page.read_text(encoding="utf-8"), module
            assert f"api/{module}.md" in nav, module
            assert (out / "api" / module / "index.html").is_file(), module

    @pytest.mark.parametrize(
        "module, symbols",
        [
            ("pipeline", ["estimate", "Estimate", "PipelineConfig"]),
            ("forest", ["VMFForest", "VMF", "sample_vmf"]),
            ("integrability", ["integrate_normals", "depth_to_mesh"]),
            ("lighting", ["render_sh", "fit_sh"]),
            ("cli", ["run_batch", "BatchItem"]),
        ],
    )
    def test_api_pages_hold_the_docstrings(self, site, module, symbols):
        out, _ = site
        html = (out / "api" / module / "index.html").read_text(encoding="utf-8")
        for symbol in symbols:
            assert f'id="sfs_torch.{module}.{symbol}"' in html, symbol
        assert not re.search(r":(math|func|class|mod):<code>", html)  # Sphinx roles are dropped

    def test_home_page_is_the_readme_with_working_links(self, site):
        out, _ = site
        html = (out / "index.html").read_text(encoding="utf-8")
        assert "Quick start" in html and "Using it" in html
        assert 'href="conventions/"' in html  # README's docs/conventions.md, relative to the site
        assert 'href="api/"' in html
