"""python -m nvs.viewer.screenshot ckpt_path=... [screenshot.out=docs/viewer.png]: a picture of the running viewer.

Starts the viewer in its own process (``nvs.viewer.process``), opens it in Debian's headless chromium
(``/usr/bin/chromium``) through Playwright, picks a gallery image, drags across the synthesised view and saves a
screenshot of the page.
"""

from __future__ import annotations

from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from nvs.core.errors import UserError
from nvs.run.cli import exits_cleanly
from nvs.run.compose import CONF_DIR
from nvs.viewer.process import ViewerProcess

CHROMIUM = Path("/usr/bin/chromium")
_IDLE = "document.body.dataset.busy === 'false' && +document.body.dataset.views >= {}"


def take(url: str, out: Path, source: int, drag: tuple[float, float]) -> None:
    from playwright.sync_api import sync_playwright

    if not CHROMIUM.is_file():
        raise UserError(f"{CHROMIUM} is missing: install Debian's chromium (scripts/install_assets.sh)")
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), headless=True)
        page = browser.new_page(viewport={"width": 960, "height": 700})
        page.goto(url)
        page.wait_for_function(_IDLE.format(1), timeout=60_000)
        views = int(page.get_attribute("body", "data-views"))
        page.locator("#gallery button").nth(source).click()
        page.wait_for_function(_IDLE.format(views + 1), timeout=60_000)
        views = int(page.get_attribute("body", "data-views"))
        box = page.locator("#drag").bounding_box()
        x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        page.mouse.move(x, y)
        page.mouse.down()
        page.mouse.move(x + drag[0] * box["width"], y - drag[1] * box["width"], steps=10)
        page.mouse.up()
        page.wait_for_function(_IDLE.format(views + 1), timeout=60_000)
        out.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(out), full_page=True)
        browser.close()


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="viewer")
@exits_cleanly
def main(cfg: DictConfig) -> None:
    overrides = [o for o in HydraConfig.get().overrides.task if not o.startswith(("screenshot.", "port="))]
    out = Path(cfg.screenshot.out)
    with ViewerProcess(overrides) as url:
        take(url, out, int(cfg.screenshot.source), tuple(float(v) for v in cfg.screenshot.drag))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
