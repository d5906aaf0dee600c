// The console: the gallery, registering by dropping a file, aligning a dropped file (or one of
// the service's recent alignments) and drawing the observed points with the reference at the
// answered pose, and detecting every part in a dropped frame. Every call goes through the
// public API (api.js), as any client's would.
//
// A dropped cloud goes to POST /points, so that the console draws exactly the points the
// service reads from the file, and as it is to POST /align (a depth image with its camera: the
// service takes the camera, [0, 0, 0], as the viewpoint unless one is typed in). A replayed
// alignment's points go back to POST /align as raw float32. A dropped frame goes to
// POST /points?pixels=true (its points, and for an organized frame each one's pixel: /detect's
// indices are pixels there) and as it is to POST /detect.

import * as api from "./api.js";
import { claims, frameCloud, radiusOf, readFrame, VERDICT_COLOURS } from "./frame.js";
import { Thumbnails, View } from "./view.js";

const OBSERVED = 0xff8c1a;
const REFERENCE = 0x3d8bff;
const DEPTH_SUFFIXES = [".png", ".tif", ".tiff", ".npy"];
const CAMERA = ["fx", "fy", "cx", "cy"];

const $ = (id) => document.getElementById(id);
const view = new View($("view"));
const thumbnails = new Thumbnails();
const referencePoints = new Map(); // name -> Float32Array, fetched once
let health = null;
let repaintFrame = null; // the drawn frame's paint(k): its colours with detection k picked out

// A DOM element: el("td", {class: "num"}, "1.5"); strings become text, never HTML.
function el(tag, attributes = {}, ...children) {
  const element = document.createElement(tag);
  for (const [name, value] of Object.entries(attributes)) {
    if (name.startsWith("on")) element.addEventListener(name.slice(2), value);
    else element.setAttribute(name, value);
  }
  element.append(...present(children));
  return element;
}

function present(children) {
  return children.filter((child) => child !== null && child !== undefined);
}

function number(value, digits = 4) {
  return value === null || value === undefined ? "—" : Number(value).toPrecision(digits);
}

function say(text, isError = false) {
  $("message").textContent = text;
  $("message").classList.toggle("error", isError);
}

function fail(error) {
  if (error instanceof api.ApiError) {
    const hint = error.status === 401 ? " (enter an API key above)" : "";
    say(`${error.status}: ${error.detail}${hint}`, true);
  } else {
    say(String(error), true);
  }
}

function table(rows) {
  return el(
    "table",
    {},
    ...rows.map(([name, value]) => el("tr", {}, el("th", {}, name), el("td", { class: "num" }, value))),
  );
}

async function pointsOf(name) {
  if (!referencePoints.has(name)) {
    const { points } = await api.floats("GET", `references/${encodeURIComponent(name)}/points`);
    referencePoints.set(name, points);
  }
  return referencePoints.get(name);
}

// Health and auth

async function refreshHealth() {
  const response = await fetch(new URL("../health", document.baseURI));
  health = await response.json();
  const auth = { open: "open (no API key configured)", keys: "API keys", "keys-for-writes": "keys for writes" };
  $("health").textContent =
    `${health.status} · ${health.references} references · ${auth[health.auth] ?? health.auth}` +
    ` · ${health.providers.join(", ")}`;
  return response.ok;
}

function readsNeedAKey() {
  return health && health.auth === "keys" && !api.apiKey();
}

// Gallery

const drawQueue = [];
let drawing = false;

async function drawThumbnails() {
  if (drawing) return;
  drawing = true;
  while (drawQueue.length) {
    const { name, canvas } = drawQueue.shift();
    try {
      thumbnails.draw({ points: await pointsOf(name), color: REFERENCE }, canvas);
    } catch (error) {
      fail(error);
    }
  }
  drawing = false;
}

const visible = new IntersectionObserver((entries) => {
  for (const entry of entries) {
    if (!entry.isIntersecting) continue;
    visible.unobserve(entry.target);
    drawQueue.push({ name: entry.target.dataset.name, canvas: entry.target.querySelector("canvas") });
  }
  drawThumbnails();
});

async function refreshGallery(select = null) {
  const { references } = await api.json("GET", "references");
  $("gallery-count").textContent = `(${references.length})`;
  const cards = references.map((reference) =>
    el(
      "div",
      { class: "card", "data-name": reference.name, title: reference.name, onclick: () => selectReference(reference) },
      el("canvas", { width: 160, height: 120 }),
      el("div", { class: "name" }, reference.name),
      el("div", { class: "muted" }, `${reference.num_points} points · scale ${number(reference.scale, 3)}`),
    ),
  );
  $("gallery").replaceChildren(...cards);
  filterGallery();
  cards.forEach((card) => visible.observe(card));
  const chosen = references.find((reference) => reference.name === select);
  if (chosen) await selectReference(chosen);
}

function filterGallery() {
  const text = $("gallery-filter").value.trim().toLowerCase();
  for (const card of $("gallery").children) card.hidden = !card.dataset.name.toLowerCase().includes(text);
}

async function selectReference(reference, selfCheck = null) {
  for (const card of $("gallery").children) card.classList.toggle("selected", card.dataset.name === reference.name);
  const points = await pointsOf(reference.name);
  view.show([{ points, color: REFERENCE }]);
  $("stage").dataset.mode = "align";
  view.element.dataset.drawn = "reference";
  const checks = el("div", {});
  const run = el("button", { onclick: () => runSelfCheck(reference.name, checks) }, "run the self-check");
  const tryIt = el(
    "button",
    { onclick: () => alignRandomPose(reference.name).catch(fail), id: "try-pose" },
    "align it in a random pose",
  );
  $("result").replaceChildren(...present([
    el("div", { class: "big" }, reference.name),
    table([
      ["points", reference.num_points],
      ["scale (radius)", number(reference.scale)],
      ["symmetry", reference.symmetry?.kind ?? "—"],
      ["points sha256", (reference.points_sha256 || "").slice(0, 16) + "…"],
    ]),
    reference.warnings?.length
      ? el("ul", { class: "reasons" }, ...reference.warnings.map((warning) => el("li", {}, warning)))
      : null,
    el("h3", {}, "Try it: half of its own points, 1 % noise, a random pose"),
    tryIt,
    el("h3", {}, "Self-check: the part aligned against random poses of itself"),
    run,
    checks,
  ]));
  if (selfCheck) showSelfCheck(selfCheck, checks);
  say(`${reference.name}: ${reference.num_points} points`);
}

async function runSelfCheck(name, into) {
  say(`self-check of ${name}…`);
  try {
    showSelfCheck(await api.json("GET", `references/${encodeURIComponent(name)}/self_check`), into);
    say(`self-check of ${name} done`);
  } catch (error) {
    fail(error);
  }
}

function showSelfCheck(checks, into) {
  into.replaceChildren(
    el(
      "table",
      {},
      el("tr", {}, el("th", {}, "render"), el("th", {}, "answered"), el("th", {}, "rotation error"), el("th", {}, "alignment error")),
      ...checks.map((check, index) =>
        el(
          "tr",
          {},
          el("td", {}, check.render ? `${index + 1} (${check.render})` : `${index + 1}`),
          el("td", {}, check.label_ok ? "right" : `WRONG: ${check.label ?? "?"}`),
          el("td", { class: "num" }, `${number(check.rotation_error_deg, 3)}°`),
          el("td", { class: "num" }, number(check.alignment_error_normalized, 3)),
        ),
      ),
    ),
  );
}

// Registering

function nameFrom(fileName) {
  const stem = fileName.replace(/\.[^.]*$/, "").replace(/[^A-Za-z0-9._-]+/g, "-");
  return stem.slice(0, 64) || "part";
}

async function register(file) {
  const name = $("register-name").value.trim() || nameFrom(file.name);
  const form = new FormData();
  form.append("name", name);
  form.append("file", file, file.name);
  const replace = $("register-replace").checked ? "true" : "";
  const reference = await api.json("POST", "references", { body: form, params: { replace } });
  referencePoints.delete(reference.name);
  document.body.dataset.registered = reference.name;
  await refreshGallery(null);
  await selectReference(reference, reference.self_check);
  say(`registered ${reference.name}: ${reference.num_points} points, scale ${number(reference.scale, 3)}`);
  refreshHealth();
}

// Aligning

function typedViewpoint() {
  const text = $("viewpoint").value.trim();
  return text ? text.split(",").map(Number) : null;
}

// The dropped file as a multipart body: a depth image (by its suffix, or an .npy with the
// camera typed in) goes with the camera's fields and the mask.
function cloudForm(file) {
  const form = new FormData();
  form.append("file", file, file.name);
  const suffix = file.name.toLowerCase().match(/\.[^.]*$/)?.[0] ?? "";
  const camera = CAMERA.filter((name) => $(name).value !== "");
  if (DEPTH_SUFFIXES.includes(suffix) && (suffix !== ".npy" || camera.length)) {
    for (const name of camera) form.append(name, $(name).value);
    if ($("depth-scale").value !== "") form.append("depth_scale", $("depth-scale").value);
    if ($("mask").files[0]) form.append("mask", $("mask").files[0], $("mask").files[0].name);
  }
  return form;
}

function alignOptions(viewpoint) {
  return {
    candidates: $("candidates").value.split(",").map((name) => name.trim()).filter(Boolean),
    min_confidence: $("min-confidence").value,
    viewpoint: viewpoint ? viewpoint.join(",") : "",
  };
}

// The points the service reads from the file (to draw them), then the file aligned as sent.
async function alignFile(file) {
  const { points, headers } = await api.floats("POST", "points", { body: cloudForm(file) });
  const implied = headers.get("X-Viewpoint");
  const viewpoint = typedViewpoint() ?? (implied ? implied.split(",").map(Number) : null);
  const form = cloudForm(file);
  for (const [name, value] of Object.entries(alignOptions(typedViewpoint()))) {
    for (const item of [].concat(value)) if (item !== "") form.append(name, item);
  }
  const answer = await api.json("POST", "align", { body: form });
  await showAlignment(points, viewpoint, answer, file.name);
  refreshRecent();
}

async function alignPoints(points, viewpoint, source) {
  const headers = { "Content-Type": "application/octet-stream" };
  const params = alignOptions(viewpoint);
  const answer = await api.json("POST", "align", { body: points, headers, params });
  await showAlignment(points, viewpoint, answer, source);
  refreshRecent();
}

async function showAlignment(points, viewpoint, answer, source, again = null) {
  const reference = await pointsOf(answer.label);
  view.show(
    [
      { points: reference, color: REFERENCE, transform: answer.transform, size: 0.8 },
      { points, color: OBSERVED }, // drawn last: the observation stays in front
    ],
    { viewpoint, axesAt: answer.transform },
  );
  $("stage").dataset.mode = "align";
  Object.assign(view.element.dataset, {
    drawn: "alignment",
    observed: points.length / 3,
    reference: reference.length / 3,
    label: answer.label,
  });
  showResult(answer, points.length / 3, source, again);
  say(`${source}: ${answer.verdict}, ${answer.label}`);
}

function showResult(answer, count, source, again) {
  const confidence =
    answer.confidence === null || answer.confidence === undefined
      ? "confidence not estimated"
      : `confidence ${(100 * answer.confidence).toFixed(0)} %`;
  const timings = Object.entries(answer.timings_ms).map(([step, ms]) => [step, `${ms.toFixed(1)} ms`]);
  $("result").replaceChildren(...present([
    el("div", { class: `verdict ${answer.verdict}`, id: "verdict" }, answer.verdict.replace("_", " ").toUpperCase()),
    el("div", { class: "big" }, answer.label),
    el("div", {}, confidence),
    answer.reasons.length ? el("ul", { class: "reasons" }, ...answer.reasons.map((reason) => el("li", {}, reason))) : null,
    table([
      ["score", number(answer.score, 3)],
      ["alignment error", number(answer.alignment_error, 3)],
      ["… of the scale", number(answer.alignment_error_normalized, 3)],
      ["hypothesis", answer.hypothesis],
      ["ambiguous", answer.ambiguous ? `yes: ${answer.alternatives.length} other pose(s)` : "no"],
      ["points set aside", answer.points_set_aside],
      ["observed points", count],
      ["from", source],
    ]),
    el("h3", {}, "Timings"),
    table(timings),
    el("h3", {}, "Candidates"),
    el(
      "table",
      {},
      el("tr", {}, el("th", {}, "label"), el("th", {}, "score"), el("th", {}, "error"), el("th", {}, "source")),
      ...answer.candidates.map((candidate) =>
        el(
          "tr",
          {},
          el("td", {}, candidate.label),
          el("td", { class: "num" }, number(candidate.score, 3)),
          el("td", { class: "num" }, number(candidate.alignment_error_normalized, 3)),
          el("td", {}, candidate.hypothesis ?? ""),
        ),
      ),
    ),
    again ? el("button", { onclick: again }, "align these points again") : null,
  ]));
}

// Every other point of a cloud with noise of 1 % of its radius, turned by a rotation uniform
// over SO(3) (Shoemake's random unit quaternion) about its centroid, shifted by up to a radius.
function randomPose(points) {
  const [a, b, c] = [Math.random(), Math.random(), Math.random()];
  const [x, y, z, w] = [
    Math.sqrt(1 - a) * Math.sin(2 * Math.PI * b),
    Math.sqrt(1 - a) * Math.cos(2 * Math.PI * b),
    Math.sqrt(a) * Math.sin(2 * Math.PI * c),
    Math.sqrt(a) * Math.cos(2 * Math.PI * c),
  ];
  const r = [
    [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
  ];
  const count = points.length / 3;
  const centre = [0, 1, 2].map((k) => points.filter((_, i) => i % 3 === k).reduce((s, v) => s + v, 0) / count);
  let radius = 0;
  for (let i = 0; i < points.length; i += 3) {
    radius = Math.max(radius, Math.hypot(points[i] - centre[0], points[i + 1] - centre[1], points[i + 2] - centre[2]));
  }
  const shift = [0, 1, 2].map(() => (2 * Math.random() - 1) * radius);
  const moved = new Float32Array(3 * Math.ceil(count / 2));
  for (let i = 0, j = 0; i < points.length; i += 6, j += 3) {
    const p = [0, 1, 2].map((k) => points[i + k] - centre[k] + 0.01 * radius * gaussian());
    for (let k = 0; k < 3; k++) moved[j + k] = centre[k] + shift[k] + r[k][0] * p[0] + r[k][1] * p[1] + r[k][2] * p[2];
  }
  return moved;
}

function gaussian() {
  return Math.sqrt(-2 * Math.log(1 - Math.random())) * Math.cos(2 * Math.PI * Math.random());
}

async function alignRandomPose(name) {
  await alignPoints(randomPose(await pointsOf(name)), null, `${name} in a random pose`);
}

// Detecting in a frame

// The frame's points as the service reads them and, for an organized frame, each one's pixel.
async function framePoints(file) {
  return readFrame(await api.call("POST", "points", { body: cloudForm(file), params: { pixels: "true" } }));
}

function detectOptions() {
  return {
    ...alignOptions(typedViewpoint()),
    max_instances: $("max-instances").value,
    roi: $("roi").value.replace(/\s+/g, ""),
  };
}

async function detectFile(file) {
  const frame = await framePoints(file);
  // the viewpoint /detect takes: the one typed in, else the file's, else the origin
  const viewpoint = typedViewpoint() ?? frame.viewpoint ?? [0, 0, 0];
  const unclaimed = new Int16Array(frame.points.length / 3).fill(-1);
  view.show([frameCloud(frame, unclaimed, [], viewpoint).cloud], { viewpoint });
  $("stage").dataset.mode = "detect";
  view.element.dataset.drawn = "frame";
  say(`${file.name}: ${frame.points.length / 3} points; detecting…`);
  const form = cloudForm(file);
  for (const [name, value] of Object.entries(detectOptions())) {
    for (const item of [].concat(value)) if (item !== "") form.append(name, item);
  }
  const answer = await api.json("POST", "detect", { body: form });
  await showDetections(frame, viewpoint, answer, file.name);
}

async function showDetections(frame, viewpoint, answer, source) {
  const { detections } = answer;
  const { owner, centres, unplaced } = claims(frame, detections);
  const { cloud, paint, drawn, tinted } = frameCloud(frame, owner, detections, viewpoint);
  repaintFrame = paint;
  const references = await Promise.all(detections.map((detection) => pointsOf(detection.label)));
  const placed = detections.map((detection, k) => {
    const radius = radiusOf(references[k]);
    return {
      points: references[k],
      color: VERDICT_COLOURS[detection.verdict],
      transform: detection.transform,
      pointSize: (2.2 * radius) / Math.sqrt(references[k].length / 3), // ~ half their spacing
      ahead: 0.25 * radius, // over the claimed points, not through the part to its far side
      tag: k,
    };
  });
  view.show([cloud, ...placed], { viewpoint, fit: placed });
  $("stage").dataset.mode = "detect";
  Object.assign(view.element.dataset, {
    drawn: "detection",
    frame: frame.points.length / 3,
    drawnPoints: drawn,
    tinted,
    detections: detections.length,
    references: references.reduce((sum, points) => sum + points.length / 3, 0),
    selected: "",
  });
  showDetectionList(answer, centres, { count: frame.points.length / 3, drawn, source, shape: frame.shape });
  const found = detections.map((d) => `${d.label} (${d.verdict.replace("_", " ")})`).join(", ");
  const warning = unplaced ? `; ${unplaced} claimed indices are not among the frame's points` : "";
  say(`${source}: ${detections.length ? found : "no registered part found"}${warning}`, unplaced > 0);
}

function showDetectionList(answer, centres, { count, drawn, source, shape }) {
  const items = answer.detections.map((detection, k) => {
    const confidence =
      detection.confidence === null || detection.confidence === undefined
        ? "confidence not estimated"
        : `confidence ${(100 * detection.confidence).toFixed(0)} %`;
    const centre = centres[k];
    const item = el(
      "li",
      {
        class: "detection",
        "data-index": k,
        "data-label": detection.label,
        "data-verdict": detection.verdict,
        "data-centre": centre ? centre.join(",") : "",
        onclick: () => selectDetection(k),
      },
      el("span", { class: `chip ${detection.verdict}` }, detection.verdict.replace("_", " ").toUpperCase()),
      el("span", { class: "label" }, detection.label),
      el("div", { class: "muted" }, `${confidence} · ${detection.num_points} points`),
      detection.reasons.length
        ? el("ul", { class: "reasons" }, ...detection.reasons.map((reason) => el("li", {}, reason)))
        : null,
      el(
        "div",
        { class: "more" },
        table([
          ["translation", detection.translation.map((v) => number(v, 4)).join(", ")],
          ["its points' centre", centre ? centre.map((v) => number(v, 4)).join(", ") : "—"],
          ["alignment error", number(detection.alignment_error, 3)],
          ["… of the scale", number(detection.alignment_error_normalized, 3)],
          ["symmetry", detection.symmetry?.kind ?? "—"],
          ["ambiguous", detection.ambiguous ? `yes: ${detection.alternatives.length} other pose(s)` : "no"],
        ]),
      ),
    );
    return item;
  });
  const total = answer.timings_ms.total;
  $("result").replaceChildren(...present([
    el("div", { class: "big" }, `${answer.detections.length} detection(s)`),
    table([
      ["frame", shape ? `${shape[1]} × ${shape[0]} pixels` : "a cloud without a grid"],
      ["points", count],
      ["drawn", drawn < count ? `${drawn} (a sample)` : drawn],
      ["supports set aside", answer.supports.length],
      ["unexplained", answer.unexplained],
      ["total", total === undefined ? "—" : `${total.toFixed(1)} ms`],
      ["from", source],
    ]),
    answer.detections.length
      ? el("ol", { id: "detections" }, ...items)
      : el("p", { id: "detections", class: "muted" }, "no registered part in the frame"),
    el("p", { class: "muted" }, "only a MATCH is safe to act on; click one to pick it out"),
  ]));
}

// Detection k picked out in the list and the view (picked again: none).
function selectDetection(k) {
  const picked = view.element.dataset.selected === String(k) ? null : k;
  for (const item of $("detections").children) {
    item.classList.toggle("selected", item.dataset.index === String(picked));
  }
  view.repaint("frame", repaintFrame(picked));
  view.highlight(picked);
  view.element.dataset.selected = picked ?? "";
}

// Recent alignments (the service's ring buffer)

async function refreshRecent() {
  const { capacity, alignments } = await api.json("GET", "alignments");
  $("recent-note").textContent = capacity
    ? `(the service keeps the last ${capacity})`
    : "(off: the service keeps none; DPC_CONSOLE__RECENT_ALIGNMENTS)";
  $("recent").replaceChildren(
    ...alignments.map((item) =>
      el(
        "li",
        { onclick: () => replay(item).catch(fail), "data-id": item.id },
        `${item.time.slice(11, 19)} ${item.label} · ${item.verdict.replace("_", " ")} · ${item.source}`,
      ),
    ),
  );
}

async function replay(item) {
  const detail = await api.json("GET", `alignments/${item.id}`);
  const { points } = await api.floats("GET", `alignments/${item.id}/points`);
  const source = `#${item.id} (${detail.source})`;
  const again = () => alignPoints(points, detail.viewpoint, `again: ${source}`).catch(fail);
  await showAlignment(points, detail.viewpoint, detail.answer, source, again);
}

// Drop zones

function dropZone(zone, input, handler) {
  const run = async (file) => {
    zone.classList.add("busy");
    say(`${file.name}…`);
    try {
      await handler(file);
    } catch (error) {
      fail(error);
    } finally {
      zone.classList.remove("busy");
    }
  };
  zone.addEventListener("click", () => input.click());
  zone.addEventListener("keydown", (event) => {
    if (event.key === "Enter" || event.key === " ") input.click();
  });
  input.addEventListener("click", (event) => event.stopPropagation());
  input.addEventListener("change", () => {
    if (input.files[0]) run(input.files[0]);
    input.value = "";
  });
  zone.addEventListener("dragover", (event) => {
    event.preventDefault();
    zone.classList.add("over");
  });
  zone.addEventListener("dragleave", () => zone.classList.remove("over"));
  zone.addEventListener("drop", (event) => {
    event.preventDefault();
    event.stopPropagation();
    zone.classList.remove("over");
    if (event.dataTransfer.files[0]) run(event.dataTransfer.files[0]);
  });
}

// Start

async function loadAll() {
  if (readsNeedAKey()) {
    say("this service needs an API key for every operation: enter it above", true);
    return;
  }
  await Promise.all([refreshGallery(), refreshRecent()]);
}

async function start() {
  for (const event of ["dragover", "drop"]) window.addEventListener(event, (e) => e.preventDefault());
  dropZone($("register-drop"), $("register-file"), register);
  dropZone($("align-drop"), $("align-file"), alignFile);
  dropZone($("detect-drop"), $("detect-file"), detectFile);
  $("gallery-filter").addEventListener("input", filterGallery);
  $("api-key").value = api.apiKey();
  $("key-form").addEventListener("submit", (event) => {
    event.preventDefault();
    api.setApiKey($("api-key").value.trim());
    say(api.apiKey() ? "the API key is set for this tab" : "no API key");
    loadAll().catch(fail);
  });
  while (!(await refreshHealth())) {
    say(health.detail || "the service is loading…");
    await new Promise((resolve) => setTimeout(resolve, 1000));
  }
  say("");
  await loadAll();
  document.body.dataset.state = "ready";
}

start().catch((error) => {
  fail(error);
  document.body.dataset.state = "failed";
});
