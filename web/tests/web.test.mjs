// Browser tests of qemd's web page: headless Debian Chromium (SwiftShader WebGL) driven by
// playwright-core, against the real `qemd serve` on 127.0.0.1 (an ephemeral port) with two
// tenants. Needs /usr/bin/chromium, `npm ci` in web/, a built qemd (QEMD_BIN, else
// ../target/release/qemd, else ../target/debug/qemd) and the shared data (QEMD_SHARED, else
// ../../shared/data beside the repository).
//
//   cd web && node --test tests/
//
// QEMD_WEB_SCREENSHOTS=dir writes a screenshot of each view there (docs/web/ holds them).
import { test, before, after } from 'node:test';
import assert from 'node:assert/strict';
import { spawn } from 'node:child_process';
import { createHash } from 'node:crypto';
import { existsSync, mkdtempSync, mkdirSync, readFileSync, rmSync, statSync } from 'node:fs';
import { tmpdir } from 'node:os';
import { dirname, join, resolve } from 'node:path';
import { fileURLToPath } from 'node:url';
import { chromium } from 'playwright-core';

const here = dirname(fileURLToPath(import.meta.url));
const repo = resolve(here, '..', '..');
const bin = process.env.QEMD_BIN || [join(repo, 'target/release/qemd'), join(repo, 'target/debug/qemd')].find(existsSync);
const shared = process.env.QEMD_SHARED || resolve(repo, '..', 'shared', 'data');
const LAS = join(shared, 'lidar/4_6_crop.las');
const MESH = join(shared, 'meshes/pairs/l0_fandisk_0.3_noisy.obj');
const COPC = join(shared, 'lidar/lone-star.copc.laz');
const shots = process.env.QEMD_WEB_SCREENSHOTS ? resolve(process.env.QEMD_WEB_SCREENSHOTS) : null;
const TOKENS = { alice: 'alice-secret-token', bob: 'bob-secret-token' };
const PREVIEW_POINTS = 20000;

let server, base, browser, dataDir;
const consoleProblems = [];
const failedResponses = [];
const choosers = [];

async function startServer() {
  dataDir = mkdtempSync(join(tmpdir(), 'qemd-web-'));
  // Small tiles, so the LAS job runs tiled (several tiles to watch), and a preview bound below
  // the LAS file's 23,875 points, so its preview is a sample.
  const env = {
    ...process.env,
    QEMD_AUTH_TOKENS: `${TOKENS.alice}:alice,${TOKENS.bob}:bob`,
    QEMD_LOG_LEVEL: 'warn',
    QEMD_JOB_TILE_POINTS: '5000',
    QEMD_PREVIEW_POINTS: String(PREVIEW_POINTS),
  };
  server = spawn(bin, ['serve', '--listen', '127.0.0.1:0', '--data-dir', join(dataDir, 'data')], { env, stdio: ['ignore', 'pipe', 'inherit'] });
  base = await new Promise((ok, fail) => {
    let out = '';
    const timer = setTimeout(() => fail(new Error(`qemd serve printed no address: ${out}`)), 30_000);
    server.stdout.on('data', (d) => {
      out += d;
      const m = out.match(/listening on (http:\/\/127\.0\.0\.1:\d+)/);
      if (m) { clearTimeout(timer); ok(m[1]); }
    });
    server.on('exit', (code) => fail(new Error(`qemd serve exited with ${code}: ${out}`)));
  });
}

async function newPage() {
  const context = await browser.newContext({ viewport: { width: 1280, height: 800 } });
  const page = await context.newPage();
  // Chromium logs every 4xx/5xx response as a console error; those are checked against the
  // ones the tests provoke (responses below), every other console error or warning fails.
  page.on('console', (m) => {
    if ((m.type() === 'error' || m.type() === 'warning') && !m.text().startsWith('Failed to load resource')) consoleProblems.push(`${m.type()}: ${m.text()}`);
  });
  page.on('response', (r) => { if (r.status() >= 400) failedResponses.push(`${r.status()} ${r.request().method()} ${new URL(r.url()).pathname}`); });
  page.on('pageerror', (e) => consoleProblems.push(`pageerror: ${e.message}`));
  page.on('filechooser', (c) => choosers.push(c));
  await page.goto(base + '/');
  await page.waitForSelector('body[data-app=ready]');
  return page;
}

async function signIn(page, token) {
  await page.fill('#token', token);
  await page.press('#token', 'Enter');
  await page.waitForSelector('#main:not([hidden])');
}

async function shot(page, name, target) {
  if (!shots) return;
  mkdirSync(shots, { recursive: true });
  await (target ? page.locator(target) : page).screenshot({ path: join(shots, `${name}.png`) });
}

async function upload(page, file) {
  await page.setInputFiles('#file', file);
  const name = file.split('/').pop();
  const li = page.locator('#uploads li', { hasText: name }).first();
  await li.locator('[data-state=done]').or(li).first().waitFor();
  await page.waitForFunction((n) => [...document.querySelectorAll('#uploads li')].some((l) => l.textContent.includes(n) && l.dataset.state !== 'uploading'), name, { timeout: 60_000 });
  assert.equal(await li.getAttribute('data-state'), 'done', await li.textContent());
  return li.getAttribute('data-upload');
}

/** Submits a job on `uploadId`; waits for it to succeed; returns its id and the percents seen. */
async function runJob(page, uploadId) {
  await page.selectOption('#input', uploadId);
  const before = new Set(await page.locator('#job-rows tr').evaluateAll((trs) => trs.map((t) => t.dataset.job)));
  await page.click('#submit');
  await page.waitForFunction((ids) => [...document.querySelectorAll('#job-rows tr')].some((t) => !ids.includes(t.dataset.job)), [...before]);
  const id = await page.locator('#job-rows tr').evaluateAll((trs, ids) => trs.find((t) => !ids.includes(t.dataset.job)).dataset.job, [...before]);
  const row = page.locator(`#job-rows tr[data-job="${id}"]`);
  const seen = [];
  const deadline = Date.now() + 240_000;
  for (;;) {
    const status = await row.getAttribute('data-status');
    seen.push(await row.locator('.pct').textContent());
    if (status === 'successful') break;
    assert.notEqual(status, 'failed', await row.textContent());
    assert.ok(Date.now() < deadline, `job ${id} did not finish: ${seen.at(-1)}`);
    await page.waitForTimeout(200);
  }
  return { id, row, seen };
}

/** Pixel statistics of the two canvases, read back through a 2D canvas. */
function pixels(page) {
  return page.evaluate(() => {
    const read = (c) => {
      const t = document.createElement('canvas');
      t.width = c.width; t.height = c.height;
      const g = t.getContext('2d');
      g.drawImage(c, 0, 0);
      return g.getImageData(0, 0, c.width, c.height).data;
    };
    const a = read(document.getElementById('view-before'));
    const b = read(document.getElementById('view-after'));
    const bg = [0x20, 0x24, 0x2c];
    const isBg = (d, i) => Math.abs(d[i] - bg[0]) + Math.abs(d[i + 1] - bg[1]) + Math.abs(d[i + 2] - bg[2]) < 6;
    let differ = 0, drawnA = 0, drawnB = 0, hot = 0, cold = 0, grey = 0, warm = 0, tinted = 0;
    const colours = new Set();
    for (let i = 0; i < a.length; i += 4) {
      if (Math.abs(a[i] - b[i]) + Math.abs(a[i + 1] - b[i + 1]) + Math.abs(a[i + 2] - b[i + 2]) > 24) differ++;
      if (!isBg(a, i)) drawnA++;
      if (!isBg(b, i)) {
        drawnB++;
        const [r, g, bl] = [b[i], b[i + 1], b[i + 2]];
        if (r > 150 && g < 140 && bl < 90) hot++;
        if (bl > 120 && r < 90) cold++;
        if (Math.abs(r - g) < 10 && Math.abs(g - bl) < 10) grey++;
        if (r > g + 20 && r > bl + 40) warm++;
        if (Math.max(r, g, bl) - Math.min(r, g, bl) > 40) tinted++;
        colours.add((r >> 4) * 256 + (g >> 4) * 16 + (bl >> 4));
      }
    }
    return { total: a.length / 4, differ, drawnA, drawnB, hot, cold, grey, warm, tinted, colours: colours.size };
  });
}

/** Runs `action` and waits until the viewer has drawn a frame after it. */
async function drawn(page, action) {
  const n = Number((await page.getAttribute('#viewer', 'data-frames')) || 0);
  await action();
  await page.waitForFunction((k) => Number(document.getElementById('viewer').dataset.frames || 0) > k, n, { timeout: 120_000 });
}

async function openViewer(page, row) {
  await drawn(page, async () => {
    await row.locator('button.view').click();
    await page.waitForSelector('#viewer[data-ready=true]', { timeout: 120_000 });
  });
}

before(async () => {
  assert.ok(bin && existsSync(bin), 'build qemd first (cargo build --release) or set QEMD_BIN');
  assert.ok([LAS, MESH, COPC].every(existsSync), `shared data missing under ${shared}`);
  await startServer();
  browser = await chromium.launch({
    executablePath: '/usr/bin/chromium',
    args: ['--use-angle=swiftshader', '--enable-unsafe-swiftshader', '--no-sandbox', '--ignore-gpu-blocklist'],
  });
});

after(async () => {
  await browser?.close();
  server?.kill('SIGTERM');
  if (dataDir) rmSync(dataDir, { recursive: true, force: true });
});

const state = {};

test('sign in: a wrong token is refused, the right one opens the page', async () => {
  const page = await newPage();
  await shot(page, '1-sign-in');
  await page.fill('#token', 'not-a-token');
  await page.click('#signin button');
  await page.waitForSelector('#signin-error:not([hidden])');
  assert.match(await page.textContent('#signin-error'), /does not know this token/);
  assert.equal(await page.isHidden('#main'), true);
  await signIn(page, TOKENS.alice);
  // The parameter form comes from the API's Params schema, defaults shown.
  const doc = await (await fetch(base + '/openapi.json')).json();
  const props = doc.components.schemas.Params.properties;
  for (const [name, p] of Object.entries(props)) {
    const input = page.locator(`[data-param="${name}"]`);
    assert.equal(await input.count(), 1, name);
    if (p.default !== undefined && typeof p.default !== 'boolean') assert.equal(await input.inputValue(), String(p.default), name);
    if (typeof p.default === 'boolean') assert.equal(await input.isChecked(), p.default, name);
  }
  state.page = page;
});

test('keyboard: Tab reaches the file picker button and Enter opens it', async () => {
  const page = state.page;
  await page.focus('#signout');
  await page.keyboard.press('Tab');
  assert.equal(await page.evaluate(() => document.activeElement.id), 'choose');
  // The listener was installed with the page (newPage): Chromium intercepts file dialogs only
  // once a listener exists, and turning that on is asynchronous.
  const n = choosers.length;
  await page.keyboard.press('Enter');
  for (let i = 0; i < 100 && choosers.length === n; i++) await page.waitForTimeout(50);
  assert.equal(choosers.length, n + 1, 'Enter on the button opened no file chooser');
  assert.equal(choosers.at(-1).isMultiple(), true);
  // Tab order reaches the parameter form after the file picker.
  await page.focus('#choose');
  await page.keyboard.press('Tab');
  assert.equal(await page.evaluate(() => document.activeElement.id), 'input');
});

test('upload a LAS file and a mesh through tus, with progress', async () => {
  const page = state.page;
  state.las = await upload(page, LAS);
  // The mesh's first PATCH is cut off: tus-js-client asks the server's offset (HEAD) and
  // resumes from it.
  const seen = [];
  let cut = false;
  await page.route('**/v1/uploads/*', (route) => {
    const m = route.request().method();
    seen.push(m);
    if (m === 'PATCH' && !cut) { cut = true; return route.abort('connectionreset'); }
    return route.continue();
  });
  state.mesh = await upload(page, MESH);
  await page.unroute('**/v1/uploads/*');
  assert.ok(cut);
  assert.deepEqual(seen.slice(0, 3), ['PATCH', 'HEAD', 'PATCH'], seen.join());
  assert.ok(state.las && state.mesh);
  const text = await page.textContent('#uploads');
  assert.match(text, /las, 23,875 points/);
  assert.match(text, /obj, 6,475 vertices/);
  // Drag and drop: a file dropped on the zone uploads the same way.
  const bunny = readFileSync(join(shared, 'meshes/bun_zipper_res4.ply'));
  const dataTransfer = await page.evaluateHandle((bytes) => {
    const dt = new DataTransfer();
    dt.items.add(new File([new Uint8Array(bytes)], 'bun_zipper_res4.ply'));
    return dt;
  }, [...bunny]);
  await page.dispatchEvent('#drop', 'drop', { dataTransfer });
  await page.waitForFunction(() => [...document.querySelectorAll('#uploads li')].some((l) => l.textContent.includes('bun_zipper_res4') && l.dataset.state === 'done'));
  assert.match(await page.textContent('#uploads'), /ply, 453 vertices/);
  const bars = await page.locator('#uploads progress').evaluateAll((b) => b.map((x) => x.value));
  assert.deepEqual(bars, [100, 100, 100]);
  await shot(page, '2-uploads-and-parameters');
});

test('an invalid parameter shows the server\'s own 422 text', async () => {
  const page = state.page;
  await page.selectOption('#input', state.las);
  await page.fill('[data-param=knn]', '2');
  await page.click('#submit');
  await page.waitForSelector('#job-error:not([hidden])');
  const shown = await page.textContent('#job-error');
  const r = await fetch(base + '/v1/jobs', {
    method: 'POST',
    headers: { Authorization: `Bearer ${TOKENS.alice}`, 'Content-Type': 'application/json' },
    body: JSON.stringify({ input: state.las, params: { knn: 2 } }),
  });
  assert.equal(r.status, 422);
  const problem = await r.json();
  assert.equal(shown, `422: ${problem.detail}`);
  assert.match(shown, /params\.knn/);
  assert.equal(await page.evaluate(() => document.activeElement.dataset.param), 'knn');
  await shot(page, '3-invalid-parameter', '#params');
  await page.click('#reset-params');
  assert.equal(await page.inputValue('[data-param=knn]'), '');
});

test('run a job on the LAS file: progress reaches 100 %, the viewer shows displacement', async () => {
  const page = state.page;
  const { id, row, seen } = await runJob(page, state.las);
  state.lasJob = id;
  assert.equal(seen.at(-1), '100 %');
  assert.equal(await row.locator('progress').evaluate((p) => p.value), 100);
  // Tiled: the tiles column counts them.
  const tiles = (await row.locator('td').nth(4).textContent()).match(/^(\d+)\/(\d+)$/);
  assert.ok(tiles && Number(tiles[2]) > 1 && tiles[1] === tiles[2], await row.textContent());
  await shot(page, '4-jobs', '#jobs');
  // Download: the result's bytes, as the API serves them.
  const [dl] = await Promise.all([page.waitForEvent('download'), row.locator('button.download').click()]);
  const path = await dl.path();
  const job = await (await fetch(`${base}/v1/jobs/${id}`, { headers: { Authorization: `Bearer ${TOKENS.alice}` } })).json();
  assert.equal(statSync(path).size, job.result.size);
  assert.equal(createHash('sha256').update(readFileSync(path)).digest('hex'), job.result.sha256);
  // Named after the input (issue 51: it was the job id).
  assert.equal(dl.suggestedFilename(), '4_6_crop.denoised.las');
  assert.equal(job.result.filename, '4_6_crop.denoised.las');
  await openViewer(page, row);
  assert.equal(await page.getAttribute('#viewer', 'data-colour'), 'displacement');
  // A bounded preview: 20,000 of the 23,875 points, the same on both sides.
  const meta = await (await fetch(`${base}/v1/jobs/${id}/preview`, { headers: { Authorization: `Bearer ${TOKENS.alice}` } })).json();
  assert.deepEqual([meta.points_total, meta.points_before, meta.points_after, meta.paired], [23875, PREVIEW_POINTS, PREVIEW_POINTS, true]);
  assert.match(await page.textContent('#viewer-info'), /20,000 of 23,875 points/);
  // Lengths in the units the file's CRS states: 4_6_crop.las is in US survey feet.
  assert.equal(meta.units, 'US ft');
  assert.match(await page.textContent('#legend-labels'), /displacement: 0 US ft/);
  assert.equal(await page.textContent('#scale-unit'), 'US ft');
  const disp = await pixels(page);
  // Both sides draw the scan; the colours are the displacement ramp's: cold points that did not
  // move and hot ones that did, in many shades.
  assert.ok(disp.drawnA > disp.total * 0.05 && disp.drawnB > disp.total * 0.05, JSON.stringify(disp));
  assert.ok(disp.cold > 200 && disp.hot > 20 && disp.colours > 20, JSON.stringify(disp));
  assert.ok(disp.differ > 0, `before and after draw the same pixels: ${JSON.stringify(disp)}`);
  await shot(page, '5-viewer-las-displacement', '#viewer');
  // Another colouring changes the picture: displacement colouring was on.
  await drawn(page, () => page.selectOption('#colour', 'plain'));
  const plain = await pixels(page);
  assert.ok(plain.grey > plain.drawnB * 0.9 && plain.hot === 0 && plain.tinted === 0, JSON.stringify(plain));
  await drawn(page, () => page.selectOption('#colour', 'class'));
  await drawn(page, () => page.selectOption('#colour', 'height'));
  await shot(page, '6-viewer-las-height', '#viewer');
  // Keyboard orbit moves the camera (the canvases are focusable).
  await page.focus('#view-after');
  const pre = await pixels(page);
  await drawn(page, () => page.keyboard.press('ArrowLeft'));
  const post = await pixels(page);
  assert.notEqual(JSON.stringify(pre), JSON.stringify(post));
});

test('reload: the uploads are listed again with their names; a job from one downloads under its name', async () => {
  const page = state.page;
  await page.reload();
  await page.waitForSelector('#main:not([hidden])');
  // The server's list (GET /v1/uploads), not the tab's memory, names them.
  await page.waitForFunction(() => document.querySelectorAll('#input option').length >= 3);
  const options = await page.locator('#input option').evaluateAll((os) => os.map((o) => [o.value, o.textContent]));
  const named = Object.fromEntries(options);
  assert.match(named[state.las], /^4_6_crop\.las \(las, 23875 points\)$/);
  assert.match(named[state.mesh], /^l0_fandisk_0\.3_noisy\.obj \(obj, /);
  // Tenant-scoped: bob's list is empty.
  const theirs = await (await fetch(`${base}/v1/uploads`, { headers: { Authorization: `Bearer ${TOKENS.bob}` } })).json();
  assert.equal(theirs.total, 0);
  // The jobs table names the input file, not its upload id.
  const lasRow = page.locator(`#job-rows tr[data-job="${state.lasJob}"]`);
  await lasRow.waitFor();
  assert.equal(await lasRow.locator('td').nth(1).textContent(), '4_6_crop.las');
  // A job started from a listed upload; its result downloads under the input's name.
  const { row } = await runJob(page, state.mesh);
  assert.equal(await row.locator('td').nth(1).textContent(), 'l0_fandisk_0.3_noisy.obj');
  const [dl] = await Promise.all([page.waitForEvent('download'), row.locator('button.download').click()]);
  assert.equal(dl.suggestedFilename(), 'l0_fandisk_0.3_noisy.denoised.obj');
  // A mesh without units is labelled in the input's units, not in metres.
  await openViewer(page, row);
  assert.equal(await page.textContent('#scale-unit'), 'input units');
  assert.match(await page.textContent('#viewer-info'), /max [0-9.e+-]+ units/);
});

test('a mesh: shaded before and after differ; flat and smooth shading; toggle layout', async () => {
  const page = state.page;
  const { id, row, seen } = await runJob(page, state.mesh);
  state.meshJob = id;
  assert.equal(seen.at(-1), '100 %');
  await openViewer(page, row);
  assert.equal(await page.isVisible('#shading-l'), true);
  const disp = await pixels(page);
  // Shaded displacement colours: most pixels tinted, from blue (still) to warm (moved most).
  assert.ok(disp.tinted > disp.drawnB * 0.5 && disp.cold > 20 && disp.warm > 20, JSON.stringify(disp));
  await drawn(page, () => page.selectOption('#colour', 'plain'));
  const smooth = await pixels(page);
  assert.ok(smooth.tinted < smooth.drawnB * 0.01, JSON.stringify(smooth));
  // The noisy input's shading is rough, the result's smooth: many pixels differ.
  assert.ok(smooth.differ > smooth.drawnA * 0.2, JSON.stringify(smooth));
  await shot(page, '7-viewer-mesh-smooth', '#viewer');
  await drawn(page, () => page.selectOption('#shading', 'flat'));
  const flat = await pixels(page);
  assert.notEqual(flat.differ, smooth.differ);
  await shot(page, '8-viewer-mesh-flat', '#viewer');
  await drawn(page, () => page.selectOption('#layout', 'toggle'));
  assert.equal(await page.getAttribute('#viewer', 'data-shown'), 'after');
  assert.equal(await page.isHidden('#view-before'), true);
  await page.focus('#view-after');
  await page.keyboard.press('t');
  assert.equal(await page.getAttribute('#viewer', 'data-shown'), 'before');
  await drawn(page, () => page.selectOption('#colour', 'displacement'));
  await shot(page, '9-viewer-toggle', '#viewer');
  await page.selectOption('#layout', 'side');
  await page.selectOption('#shading', 'smooth');
});

test('live progress of a long job (phase, tiles, percent, ETA), then Cancel stops it', async () => {
  const page = state.page;
  // 518,862 points in tiles of 5,000: minutes of work, watched for a few seconds.
  const id = await upload(page, COPC);
  await page.selectOption('#input', id);
  const known = new Set((await page.locator('#job-rows tr').evaluateAll((trs) => trs.map((t) => t.dataset.job))));
  await page.click('#submit');
  await page.waitForFunction((ids) => [...document.querySelectorAll('#job-rows tr')].some((t) => !ids.includes(t.dataset.job)), [...known]);
  const job = await page.locator('#job-rows tr').evaluateAll((trs, ids) => trs.find((t) => !ids.includes(t.dataset.job)).dataset.job, [...known]);
  const row = page.locator(`#job-rows tr[data-job="${job}"]`);
  // Wait until a few tiles are done and the page shows an ETA.
  await page.waitForFunction((j) => {
    const tr = document.querySelector(`#job-rows tr[data-job="${j}"]`);
    const m = tr.cells[4].textContent.match(/^(\d+)\/(\d+)$/);
    return tr.dataset.status === 'running' && tr.cells[3].textContent === 'tiles' && m && Number(m[1]) >= 8 && tr.cells[6].textContent !== '';
  }, job, { timeout: 180_000 });
  const cells = await row.locator('td').allTextContents();
  const [done, total] = cells[4].split('/').map(Number);
  assert.ok(done < total, cells.join(' | '));
  const percent = Number(cells[5].replace(/[^0-9.]/g, ''));
  assert.ok(percent > 0 && percent < 100, cells.join(' | '));
  assert.match(cells[6], /^\d+ (s|min)$/);
  await shot(page, '4b-job-running', '#jobs');
  assert.equal(await row.locator('button.cancel').textContent(), 'Cancel');
  const t0 = Date.now();
  await row.locator('button.cancel').click();
  await page.waitForFunction((j) => document.querySelector(`#job-rows tr[data-job="${j}"]`).dataset.status === 'dismissed', job);
  assert.ok(Date.now() - t0 < 5000, `cancel took ${Date.now() - t0} ms`);
  const r = await fetch(`${base}/v1/jobs/${job}`, { headers: { Authorization: `Bearer ${TOKENS.alice}` } });
  assert.equal((await r.json()).status, 'dismissed');
  assert.equal(await row.locator('button.cancel').isHidden(), true);
});

test('tenancy: another token sees neither the jobs nor the previews', async () => {
  const page = await newPage();
  await signIn(page, TOKENS.bob);
  await page.waitForTimeout(500);
  assert.equal(await page.locator('#job-rows tr').count(), 0);
  assert.equal(await page.isVisible('#jobs-empty'), true);
  const statuses = await page.evaluate(async ([ids, token]) => {
    const out = [];
    for (const id of ids) {
      for (const p of ['', '/preview', '/preview/before', '/preview/after', '/result']) {
        const r = await fetch(`/v1/jobs/${id}${p}`, { headers: { Authorization: `Bearer ${token}` } });
        out.push(r.status);
      }
    }
    return out;
  }, [[state.lasJob, state.meshJob], TOKENS.bob]);
  assert.deepEqual(statuses, Array(10).fill(404));
  await page.context().close();
});

test('cancel: a dismissed job leaves the list of actions, and the page logged no errors', async () => {
  const page = state.page;
  const row = page.locator(`#job-rows tr[data-job="${state.lasJob}"]`);
  await row.locator('button.cancel').click();
  await page.waitForFunction((id) => document.querySelector(`#job-rows tr[data-job="${id}"]`).dataset.status === 'dismissed', state.lasJob);
  const r = await fetch(`${base}/v1/jobs/${state.lasJob}/preview`, { headers: { Authorization: `Bearer ${TOKENS.alice}` } });
  assert.equal(r.status, 404);
  assert.deepEqual(consoleProblems, []);
  // The only failed requests are the ones provoked: the wrong token, the invalid knn, and bob's
  // look at alice's jobs.
  const provoked = /^(401 GET \/v1\/jobs|422 POST \/v1\/jobs|404 GET \/v1\/jobs\/[0-9a-f-]{36}(\/preview(\/before|\/after)?|\/result)?)$/;
  assert.deepEqual(failedResponses.filter((r) => !provoked.test(r)), []);
  assert.ok(failedResponses.length >= 12, failedResponses.join('\n'));
});

test('a server without tokens opens the page without asking for one', async () => {
  const dir = mkdtempSync(join(tmpdir(), 'qemd-web-open-'));
  const open = spawn(bin, ['serve', '--listen', '127.0.0.1:0', '--data-dir', join(dir, 'data')], {
    env: { ...process.env, QEMD_AUTH_TOKENS: '', QEMD_LOG_LEVEL: 'warn' },
    stdio: ['ignore', 'pipe', 'inherit'],
  });
  try {
    const url = await new Promise((ok, fail) => {
      let out = '';
      const timer = setTimeout(() => fail(new Error(`no address: ${out}`)), 30_000);
      open.stdout.on('data', (d) => {
        out += d;
        const m = out.match(/listening on (http:\/\/127\.0\.0\.1:\d+)/);
        if (m) { clearTimeout(timer); ok(m[1]); }
      });
    });
    const context = await browser.newContext();
    const page = await context.newPage();
    await page.goto(url + '/');
    await page.waitForSelector('#main:not([hidden])');
    assert.equal(await page.isHidden('#signin'), true);
    assert.equal(await page.isHidden('#signout'), true);
    assert.match(await page.textContent('#whoami'), /no token needed/);
    // The drop zone names every format it takes.
    assert.match(await page.textContent('#drop-help'), /COPC, E57/);
    // The few fields a LiDAR user sets are shown; the rest fold under Advanced.
    for (const p of ['method', 'knn', 'max_move', 'classes', 'outliers']) assert.equal(await page.isVisible(`[data-param=${p}]`), true, p);
    assert.equal(await page.isVisible('[data-param=sigma_r]'), false);
    await page.click('details.advanced summary');
    assert.equal(await page.isVisible('[data-param=sigma_r]'), true);
    await context.close();
  } finally {
    open.kill('SIGTERM');
    rmSync(dir, { recursive: true, force: true });
  }
});
