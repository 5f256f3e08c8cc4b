// Opens Foxglove Studio (the prebuilt browser bundle of @foxglove/studio-base 1.48.0, served
// by serve.py) in headless Chromium, connects it to a live twinswarm run, turns on the 3D
// panel's scene topics and takes a screenshot. Run by run.sh:
//   node shot.mjs PAGE_URL WS_URL OUT.png
import { chromium } from "playwright-core";

const [pageUrl, wsUrl, out] = process.argv.slice(2);
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium",
  args: ["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"],
});
try {
  const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
  page.on("pageerror", (e) => console.log("page error:", String(e).slice(0, 300)));
  await page.goto(`${pageUrl}/?ds=foxglove-websocket&ds.url=${encodeURIComponent(wsUrl)}`, {
    waitUntil: "load",
    timeout: 120000,
  });
  // Connected once the server's channels are listed.
  await page.getByText("/scene/arena").first().waitFor({ timeout: 60000 });
  await page.waitForTimeout(3000);
  // The 3D panel's settings: turn on both SceneUpdate topics (Studio 1.48 starts them hidden).
  await page.getByText("3D", { exact: true }).first().hover();
  await page.getByRole("button", { name: "Settings" }).first().click();
  await page.getByText("3D panel settings").waitFor();
  for (const topic of ["/scene/arena", "/scene/copters"]) {
    const row = await page.getByText(topic, { exact: true }).last().boundingBox();
    const toggles = page.locator('button[title="Toggle visibility"], [aria-label="Toggle visibility"]');
    let clicked = false;
    for (let i = 0; i < (await toggles.count()); i++) {
      const b = await toggles.nth(i).boundingBox();
      if (b && Math.abs(b.y + b.height / 2 - (row.y + row.height / 2)) < 12) {
        await toggles.nth(i).click();
        clicked = true;
        break;
      }
    }
    if (!clicked) await page.mouse.click(402, row.y + row.height / 2);
  }
  await page.waitForTimeout(1500);
  // Closer to the arena.
  await page.mouse.move(720, 430);
  for (let i = 0; i < Number(process.env.ZOOM ?? 9); i++) {
    await page.mouse.wheel(0, -120);
    await page.waitForTimeout(150);
  }
  await page.waitForTimeout(4000);
  await page.screenshot({ path: out });
  console.log("wrote", out);
  // What Studio makes of the run's clock (start time, current time): its data source panel,
  // the first icon of the left bar, beside the 3D view.
  if (process.env.SOURCE_SHOT) {
    await page.mouse.click(25, 25);
    await page.waitForTimeout(1500);
    await page.screenshot({ path: process.env.SOURCE_SHOT });
    console.log("wrote", process.env.SOURCE_SHOT);
  }
} finally {
  await browser.close();
}
