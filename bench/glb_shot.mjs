// Screenshot of a page once every <model-viewer> on it has loaded and shows its model (Chrome DevTools protocol,
// Node's WebSocket): headless Chromium's --screenshot fires before a GLB of a few MB has even been decoded.
//   node --experimental-websocket bench/glb_shot.mjs PAGE.html OUT.png WIDTH HEIGHT
import { spawn } from 'node:child_process';
import { mkdtempSync, writeFileSync, rmSync } from 'node:fs';
import { tmpdir } from 'node:os';
import { join, resolve } from 'node:path';

const [page, out, width = '880', height = '660'] = process.argv.slice(2);
const port = 9300 + Math.floor(Math.random() * 500);
const profile = mkdtempSync(join(tmpdir(), 'glb-shot-'));
const chrome = spawn(process.env.CHROMIUM || 'chromium', ['--headless', '--no-sandbox', '--disable-gpu',
  '--use-gl=swiftshader', '--enable-unsafe-swiftshader', '--no-first-run', `--user-data-dir=${profile}`,
  `--remote-debugging-port=${port}`, `--window-size=${width},${height}`, 'about:blank'], { stdio: 'ignore' });
const sleep = ms => new Promise(r => setTimeout(r, ms));
const quit = async code => {
  const gone = new Promise(r => chrome.once('exit', r));
  chrome.kill();
  await gone;  // Chromium writes its profile until it exits
  rmSync(profile, { recursive: true, force: true });
  process.exit(code);
};
let targets = null;
for (let i = 0; i < 100 && !targets; i++) {
  try { targets = await (await fetch(`http://127.0.0.1:${port}/json`)).json(); } catch { await sleep(200); }
}
if (!targets) { console.error('glb_shot: Chromium did not start'); await quit(1); }
const ws = new WebSocket(targets.find(t => t.type === 'page').webSocketDebuggerUrl);
await new Promise(r => { ws.onopen = r; });
let id = 0;
const pending = new Map();
ws.onmessage = m => { const d = JSON.parse(m.data); pending.get(d.id)?.(d); pending.delete(d.id); };
const send = (method, params = {}) => new Promise(r => { pending.set(++id, r); ws.send(JSON.stringify({ id, method, params })); });
await send('Emulation.setDeviceMetricsOverride', { width: +width, height: +height, deviceScaleFactor: 1,
  mobile: false });
await send('Page.navigate', { url: 'file://' + resolve(page) });
const ready = "[...document.querySelectorAll('model-viewer')].every(v => v.loaded && v.modelIsVisible) && " +
  "document.querySelectorAll('model-viewer').length > 0";
let ok = false;
for (let i = 0; i < 300 && !ok; i++) {
  await sleep(1000);
  ok = (await send('Runtime.evaluate', { expression: ready, returnByValue: true })).result?.result?.value === true;
}
if (!ok) { console.error(`glb_shot: ${page}: the viewers did not show their models in 300 s`); await quit(1); }
await sleep(3000);  // the first frames after the load event
const shot = await send('Page.captureScreenshot', { format: 'png' });
writeFileSync(out, Buffer.from(shot.result.data, 'base64'));
await quit(0);
