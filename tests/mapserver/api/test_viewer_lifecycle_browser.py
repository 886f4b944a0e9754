"""The viewer's map lifecycle in a real browser (issue 65): delete with a confirmation, restore, rename.

A live ``serve`` holds two small maps. With a write token the maps table offers rename and delete; deleting
asks first (cancel keeps the map), and "show deleted maps" lists the archived map with a restore button. With
a read token none of it is shown. The delete confirmation's screenshot goes to the test's tmp dir (copied to
``docs/screenshots/8-delete-map.png``).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.mapserver.api.conftest import Server, free_port, make_token
from tests.mapserver.api.test_map_lifecycle import _store
from tests.mapserver.api.test_viewer_browser import browser  # noqa: F401 (the fixture)

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """A served database with the maps ``lab`` and ``yard``, a write and a read token."""
    folder = tmp_path_factory.mktemp("lifecycle")
    db_url = f"sqlite:///{folder / 'viewer.db'}"
    _store(db_url, "lab", 3)
    _store(db_url, "yard", 5)
    tokens = {scope: make_token(db_url, scope) for scope in ("write", "read")}
    server = Server(db_url, folder / "uploads", free_port(), folder / "server.log")
    server.start()
    try:
        yield {"url": server.url, "tokens": tokens}
    finally:
        server.stop()


def _page(browser: Any, live: dict[str, Any], scope: str) -> Any:  # noqa: F811
    context = browser.new_context(viewport={"width": 1200, "height": 700})
    page = context.new_page()
    page.set_default_timeout(20_000)
    page.goto(live["url"] + "/")
    page.fill("#token", live["tokens"][scope])
    page.click("#token-form button[type=submit]")
    page.wait_for_selector("#maps-table tbody tr")
    return page


def _listed(page: Any, table: str = "#maps-table") -> list[str]:
    return list(page.eval_on_selector_all(f"{table} tbody tr", "rows => rows.map(r => r.dataset.map)"))


def test_delete_asks_first_then_restore_and_rename(browser: Any, live: dict[str, Any], tmp_path: Path) -> None:  # noqa: F811
    page = _page(browser, live, "write")
    errors: list[str] = []
    page.on("pageerror", lambda err: errors.append(str(err)))
    page.wait_for_selector("tr[data-map=lab] .map-delete")
    assert _listed(page) == ["lab", "yard"]
    # delete asks first; cancel keeps the map
    page.click("tr[data-map=lab] .map-delete")
    page.wait_for_selector("#dialog-backdrop:not([hidden])")
    assert page.inner_text("#dialog-title") == "Delete map “lab”?"
    assert "archived, not destroyed" in page.inner_text("#dialog-text")
    page.screenshot(path=str(tmp_path / "8-delete-map.png"))
    page.click("#dialog-cancel")
    assert page.is_hidden("#dialog-backdrop") and _listed(page) == ["lab", "yard"]
    # confirmed: the map leaves the table and is listed among the deleted maps, restorable
    page.click("tr[data-map=lab] .map-delete")
    page.click("#dialog-ok")
    page.wait_for_function("() => !document.querySelector('#maps-table tr[data-map=lab]')")
    assert _listed(page) == ["yard"] and "deleted" in page.inner_text("#banner")
    page.click("#show-archived")
    page.wait_for_selector("#archived-table tr[data-map=lab] .map-restore")
    page.click("#archived-table tr[data-map=lab] .map-restore")
    page.wait_for_selector("#maps-table tr[data-map=lab]")
    assert _listed(page) == ["lab", "yard"]
    page.wait_for_selector("#archived-empty:not([hidden])")
    # rename: a name that breaks the rule is shown in the dialog, a good one renames
    page.click("tr[data-map=yard] .map-rename")
    page.fill("#dialog-input", "a/b")
    page.click("#dialog-ok")
    page.wait_for_function("() => document.querySelector('#dialog-error').textContent.includes('invalid map name')")
    page.fill("#dialog-input", "yard-2")
    page.click("#dialog-ok")
    page.wait_for_selector("#maps-table tr[data-map=yard-2]")
    assert _listed(page) == ["lab", "yard-2"] and page.is_hidden("#dialog-backdrop")
    assert errors == []
    page.context.close()


def test_a_read_token_sees_no_lifecycle_actions(browser: Any, live: dict[str, Any]) -> None:  # noqa: F811
    page = _page(browser, live, "read")
    page.wait_for_function("() => document.querySelectorAll('#maps-table tbody tr').length >= 2")
    assert page.locator(".map-delete, .map-rename").count() == 0
    assert page.is_hidden("#archived-box")
    page.context.close()


def _sent_fields(page: Any, tmp_path: Path) -> dict[str, str]:
    """Upload a small file from the form and return the text fields of the form the page sent."""
    log = tmp_path / "walk.bag"
    log.write_bytes(b"not a bag")
    page.set_input_files("#upload-file", str(log))
    page.evaluate("""() => {
      window.sentForms = [];
      if (!window.plainFetch) window.plainFetch = window.fetch;
      window.fetch = (url, options) => {
        if (options && options.body instanceof FormData) {
          const texts = [...options.body.entries()].filter(([, v]) => typeof v === "string");
          window.sentForms.push(Object.fromEntries(texts));
        }
        return window.plainFetch(url, options);
      };
    }""")
    page.click("#upload-form button[type=submit]")
    page.wait_for_function("() => window.sentForms.length === 1")
    return dict(page.evaluate("() => window.sentForms[0]"))


def test_the_upload_form_merges_into_a_chosen_map(browser: Any, live: dict[str, Any], tmp_path: Path) -> None:  # noqa: F811
    page = _page(browser, live, "write")
    page.goto(live["url"] + "/#/jobs")
    page.wait_for_selector("#upload-into option[value=lab]", state="attached")
    choices = page.eval_on_selector_all("#upload-into option", "os => os.map(o => o.value)")
    assert choices[0] == "" and "lab" in choices and len(choices) == 3  # the live maps (the other may be renamed)
    page.fill("#upload-map", "walk")
    plain = _sent_fields(page, tmp_path)  # no map chosen: the name is a new map's, and no "into" is sent
    assert plain.get("map") == "walk" and "into" not in plain
    page.select_option("#upload-into", "lab")
    assert page.is_disabled("#upload-map") and page.is_disabled("#upload-merge")
    into = _sent_fields(page, tmp_path)  # "into": the map's name, no new map's name, merging on
    assert into.get("into") == "lab" and "map" not in into and into.get("merge") == "true"
