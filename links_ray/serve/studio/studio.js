// The studio page: wires the editor, the draw-to-retrieve panel and the save/share buttons,
// and shows every failure in words in the error banner or next to what failed.

import { explain, getJson, limits, loadLimits, postForFile } from "./api.js";
import { Constraints } from "./constraints.js";
import { readCurveFile } from "./curvefile.js";
import { Editor } from "./editor.js";
import { download, mechanismJson, mechanismSvg, readMechanismFile, sharedMechanism, shareUrl } from "./files.js";
import { KitView } from "./kit.js";
import { FIXED } from "./mechanism.js";
import { Retriever } from "./retrieve.js";

const $ = (id) => document.getElementById(id);

// The banner holds one message per source, so clearing a network error does not hide another.
const banner = $("error");
const messages = new Map();
function notify(message, source = "page") {
  if (message) messages.set(source, message);
  else messages.delete(source);
  banner.textContent = [...messages.values()].join(" ");
  banner.hidden = messages.size === 0;
}
banner.addEventListener("click", () => {
  messages.clear();
  notify("");
});

// Nothing fails silently: whatever escapes a handler reaches the banner too.
window.addEventListener("error", (e) => notify(`Unexpected error: ${e.message}`, "unexpected"));
window.addEventListener("unhandledrejection", (e) => {
  const reason = e.reason && e.reason.message ? e.reason.message : String(e.reason);
  notify(`Unexpected error: ${reason}`, "unexpected");
});

const editor = new Editor({
  canvas: $("studio-canvas"),
  notify,
  ui: {
    hint: $("hint"),
    play: $("play"),
    crank: $("crank"),
    crankValue: $("crank-value"),
    dof: $("dof"),
    solvable: $("solvable"),
    status: $("status"),
    latency: $("latency"),
    rules: $("rules"),
    lock: $("lock"),
    undo: $("undo"),
    redo: $("redo"),
    tools: [...document.querySelectorAll("[data-tool]")],
  },
});

// The boxes are drawn on the draw canvas, which repaints when they change.
const constraints = new Constraints({
  ui: {
    pivots: $("box-pivots"),
    footprint: $("box-footprint"),
    clear: $("clear-boxes"),
    maxLinkRatio: $("max-link-ratio"),
    minLink: $("min-link"),
    maxLink: $("max-link"),
  },
  onChange: () => retriever.paint(),
});

const retriever = new Retriever({
  canvas: $("draw-canvas"),
  notify,
  editor,
  constraints,
  ui: {
    retrieve: $("retrieve"),
    synthesize: $("synthesize"),
    clear: $("clear-drawing"),
    open: $("open-in-editor"),
    k: $("k"),
    minTransmission: $("min-transmission"),
    status: $("retrieve-status"),
    list: $("results"),
    maxJoints: $("max-joints"),
    front: $("front"),
    timed: $("timed"),
    partial: $("partial"),
    frontTable: $("front-table"),
    unmet: $("unmet"),
  },
});

// Build: the editor's mechanism as a kit of printable parts, in 3D (POST /api/kit).
const kitView = new KitView({
  editor,
  notify,
  ui: {
    build: $("build-kit"),
    layers: $("kit-layers"),
    panel: $("kit-panel"),
    status: $("kit-status"),
    canvas: $("kit-canvas"),
    play: $("kit-play"),
    crank: $("kit-crank"),
    crankValue: $("kit-crank-value"),
    explode: $("kit-explode"),
    explodeValue: $("kit-explode-value"),
    close: $("kit-close"),
    downloads: { zip: $("kit-zip"), glb: $("kit-glb"), bom: $("kit-bom") },
    crankMm: $("crank-mm"),
    barWidth: $("kit-bar-width"),
    clearance: $("kit-clearance"),
    layerThickness: $("kit-layer-thickness"),
    base: $("kit-base"),
  },
});

for (const button of document.querySelectorAll("[data-tool]")) {
  button.addEventListener("click", () => editor.setTool(button.dataset.tool));
}
$("undo").addEventListener("click", () => editor.undo());
$("redo").addEventListener("click", () => editor.redo());
$("new").addEventListener("click", () => editor.reset());
$("fit").addEventListener("click", () => editor.fit());
$("play").addEventListener("click", () => editor.setPlaying(!editor.playing));
$("crank").addEventListener("input", (e) => {
  editor.setPlaying(false); // the user has taken the crank
  editor.setStep(Number(e.target.value));
});

// -- save and share ---------------------------------------------------------------------------

$("export-json").addEventListener("click", () => {
  download("mechanism.json", mechanismJson(editor.current()), "application/json");
});
$("export-svg").addEventListener("click", () => {
  const sim = editor.sim;
  const trajectories = sim.version === editor.version ? editor.trajectories() : null;
  const lock = sim.state === "locking" ? sim.lock : null;
  download("mechanism.svg", mechanismSvg(editor.current(), trajectories, lock), "image/svg+xml");
  if (!trajectories) notify("The SVG has no paths: the mechanism is not simulated yet.", "export");
  else notify("", "export");
});
// Fabrication files come from the server (/api/export), drawn by the engine in millimetres.
// The selected joint's path goes in too, when the mechanism turns fully.
let exporting = 0;
async function exportForFabrication(format) {
  const mech = editor.current();
  const body = { ...mech, format, crank_mm: Number($("crank-mm").value) };
  const joint = editor.selected;
  if (joint >= 0 && mech.node_types[joint] !== FIXED && editor.sim.state === "ok") {
    body.path_joint = joint;
  }
  exporting += 1;
  try {
    const answer = await postForFile("/api/export", body, `mechanism.${format}`);
    if (answer.status === 200) {
      download(answer.name, answer.blob, answer.type);
      notify("", "fabrication");
    } else {
      notify(`Export failed: ${explain(answer)}`, "fabrication");
    }
  } catch (err) {
    notify(`Export failed: ${err.message}`, "fabrication");
  } finally {
    exporting -= 1;
  }
}
$("export-fab-svg").addEventListener("click", () => exportForFabrication("svg"));
$("export-dxf").addEventListener("click", () => exportForFabrication("dxf"));
$("export-table").addEventListener("click", () => exportForFabrication("table"));
$("import-json").addEventListener("click", () => $("import-file").click());
// Files being read: the page is not idle until an import has reached the editor.
let importing = 0;
$("import-file").addEventListener("change", async (e) => {
  const file = e.target.files[0];
  e.target.value = ""; // choosing the same file again still fires a change
  if (!file) return;
  importing += 1;
  try {
    editor.load(await readMechanismFile(file));
    notify("", "import");
  } catch (err) {
    notify(`Import failed: ${err.message}`, "import");
  } finally {
    importing -= 1;
  }
});
// A curve from a drawing's file: the server reads it (one parser for the CLI and the page).
let openingCurve = 0;
$("open-curve").addEventListener("click", () => $("curve-file").click());
$("curve-file").addEventListener("change", async (e) => {
  const file = e.target.files[0];
  e.target.value = ""; // choosing the same file again still fires a change
  if (!file) return;
  openingCurve += 1;
  try {
    const id = $("curve-id").value.trim();
    const curve = await readCurveFile(file, id);
    retriever.openCurve(curve.points, curve.closed, id ? `${file.name}#${id}` : file.name);
    notify("", "curve");
  } catch (err) {
    notify(`Cannot open the curve: ${err.message}`, "curve");
  } finally {
    openingCurve -= 1;
  }
});
$("share").addEventListener("click", async () => {
  const url = shareUrl(editor.current());
  history.replaceState(null, "", url);
  try {
    await navigator.clipboard.writeText(url);
    editor.refuse("Link copied: it opens this mechanism in the studio.");
  } catch {
    editor.refuse("The page address now holds this mechanism: copy it from the address bar.");
  }
});

// -- keyboard ---------------------------------------------------------------------------------

document.addEventListener("keydown", (e) => {
  const target = e.target;
  if (target instanceof HTMLInputElement || target instanceof HTMLTextAreaElement) return;
  if (target instanceof HTMLButtonElement && (e.key === " " || e.key === "Enter")) return;
  if (editor.key(e)) e.preventDefault();
});

// -- start ------------------------------------------------------------------------------------

try {
  const shared = sharedMechanism();
  if (shared) editor.load(shared, { play: true }); // the page opens moving, as on its own
} catch (err) {
  notify(`The shared link could not be opened: ${err.message}`, "share");
}

// The inputs' bounds are the API's own limits, not numbers of the page's.
let limitsSettled = false;
loadLimits()
  .then(() => {
    $("k").min = String(limits.min_k);
    $("k").max = String(limits.max_k);
    $("min-transmission").max = String(limits.max_transmission_deg);
    $("min-transmission").value = String(limits.default_transmission_deg);
    $("max-joints").min = String(limits.min_joints);
  })
  .catch((err) => notify(`The API's limits could not be read: ${err.message}`, "limits"))
  .finally(() => (limitsSettled = true));

getJson("/api/health")
  .then((answer) => {
    const health = $("health");
    if (answer.status === 200) {
      health.textContent = `${answer.data.paths.toLocaleString("en")} curated paths to search`;
    } else {
      health.textContent = "server unhealthy";
      notify(`Health check failed: ${explain(answer)}`, "health");
    }
  })
  .catch((err) => notify(`Health check failed: ${err.message}`, "health"));

// For scripts and the browser tests: the live state, read-only by convention. `kitView` is
// the kit in 3D: its parts() are the parts drawn (kind, name, layer, world position in mm, z
// up, and a bar's two hole centres) at its current step, which setStep(s) sets; drawn() says
// what the last frame drew.
window.studio = {
  editor,
  retriever,
  constraints,
  kitView,
  limits,
  mechanism: () => editor.current(),
  trajectories: () => editor.trajectories(),
  toScreen: (p) => editor.view.toScreen(p),
  drawToScreen: (p) => retriever.view.toScreen(p),
  latencies: () => editor.latencies.slice(),
  idle: () =>
    limitsSettled &&
    importing === 0 &&
    exporting === 0 &&
    openingCurve === 0 &&
    editor.idle &&
    kitView.idle,
};
