// IllumiNet-edge /viewer: a glTF model lit by the live lighting estimate (docs/estimate.md).
//
// The estimate arrives as Server-Sent Events from /estimates, one JSON object per event in the shape
// of WebXR's XRLightEstimate, and is applied the way three.js's XREstimatedLight applies a WebXR
// estimate: sphericalHarmonicsCoefficients straight into a LightProbe, the primary light into a
// DirectionalLight (colour normalised, the scalar as intensity, placed along the direction). The
// scene is the anchor's frame: +Y up, metres, the model standing on y = 0. Light values are in the
// camera picture's linear units, so under NoToneMapping a white diffuse surface shows what the camera
// would record; the default Neutral tone mapping only compresses highlights.
//
// window.illuminetViewer exposes the state (estimates received, model loaded, frames rendered,
// errors) for scripts and the browser tests.

import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

const params = new URLSearchParams(location.search);
const TONEMAPS = {
  neutral: THREE.NeutralToneMapping, aces: THREE.ACESFilmicToneMapping, agx: THREE.AgXToneMapping,
  none: THREE.NoToneMapping,
};
// Every query parameter the page reads: a bad value (?exposure=abc drew a black canvas) falls back to
// the default, and a note on the status line names it, what was expected and what is used instead.
const paramNotes = [];
function param(name, fallback, parse, expected) {
  const raw = params.get(name);
  if (raw === null) return fallback;
  const v = parse(raw);
  if (v !== undefined) return v;
  paramNotes.push(`?${name}=${raw.slice(0, 40)}: expected ${expected}; using ${name}=${String(fallback)}`);
  return fallback;
}
const flag = (raw) => (raw === "1" ? true : raw === "0" ? false : undefined);
const withBackground = param("background", false, flag, "1 or 0");
const showUi = param("ui", true, flag, "1 or 0");
const exposure = param("exposure", 1, (raw) => {
  const v = Number(raw);
  return raw.trim() !== "" && Number.isFinite(v) && v > 0 ? v : undefined;
}, "a number > 0");
const tonemapName = param("tonemap", "neutral", (raw) => (Object.hasOwn(TONEMAPS, raw) ? raw : undefined),
  Object.keys(TONEMAPS).join(", "));
const tonemap = TONEMAPS[tonemapName];

const state = { estimates: 0, frameId: null, last: null, modelLoaded: false, rendered: 0, errors: [] };
window.illuminetViewer = state;
window.addEventListener("error", (e) => state.errors.push(String(e.message || e)));

const stage = document.getElementById("stage");
const statusEl = document.getElementById("status");
if (!showUi) statusEl.style.display = "none";
// the status line: a problem (the model, WebGL) stays on it, shown even with ui=0, above the
// connection's state and the latest estimate's figures
const status = { params: paramNotes.join("\n"), problem: "", connection: "", estimate: "loading…" };
function showStatus() {
  statusEl.textContent = [status.params, status.problem, status.connection, status.estimate].filter(Boolean)
    .join("\n");
  if (status.params || status.problem) statusEl.style.display = "";
}
if (status.params) showStatus();

// ---- camera picture behind the model (background=1)
let bgImage = null;
if (withBackground) {
  bgImage = document.createElement("img");
  bgImage.alt = "camera";
  bgImage.src = "/stream.mjpg?source=camera";
  stage.appendChild(bgImage);
}

// ---- renderer, scene, lights
let renderer;
try {
  renderer = new THREE.WebGLRenderer({ antialias: true, alpha: withBackground });
} catch (err) {  // no WebGL (disabled, blocklisted GPU): say so rather than "loading…" for ever
  status.problem = "this browser cannot draw the viewer: WebGL is not available (" + (err.message || err) + ")";
  showStatus();
  throw err;
}
renderer.setPixelRatio(Math.min(window.devicePixelRatio, 2));
renderer.outputColorSpace = THREE.SRGBColorSpace;
renderer.toneMapping = tonemap;
renderer.toneMappingExposure = exposure;
renderer.shadowMap.enabled = true;
renderer.shadowMap.type = THREE.PCFShadowMap;  // (PCFSoftShadowMap was removed in r18x)
stage.appendChild(renderer.domElement);

const scene = new THREE.Scene();
if (!withBackground) scene.background = new THREE.Color(0x1a1a1a);

const probe = new THREE.LightProbe();  // ambient radiance SH; intensity 1 as XREstimatedLight
scene.add(probe);
const sun = new THREE.DirectionalLight(0xffffff, 0);  // the primary light; off until an estimate says
sun.castShadow = true;
sun.shadow.mapSize.set(1024, 1024);
sun.shadow.bias = -0.0005;
sun.shadow.normalBias = 0.01;
scene.add(sun);
scene.add(sun.target);

// the floor under the model: grey and lit without a background; only its shadow over the camera picture
const groundMaterial = withBackground
  ? new THREE.ShadowMaterial({ opacity: 0.45 })
  : new THREE.MeshStandardMaterial({ color: 0x808080, roughness: 1.0, metalness: 0.0 });
const ground = new THREE.Mesh(new THREE.CircleGeometry(1, 96), groundMaterial);
ground.rotation.x = -Math.PI / 2;
ground.receiveShadow = true;
scene.add(ground);

const camera = new THREE.PerspectiveCamera(35, 1, 0.01, 100);
const controls = new OrbitControls(camera, renderer.domElement);
controls.enableDamping = true;
controls.enabled = !withBackground;

let modelCentre = new THREE.Vector3(0, 0.1, 0);
let modelRadius = 0.15;

function frameModel(object) {
  const box = new THREE.Box3().setFromObject(object);
  const sphere = box.getBoundingSphere(new THREE.Sphere());
  modelCentre = sphere.center.clone();
  modelRadius = Math.max(sphere.radius, 1e-3);
  ground.scale.setScalar(modelRadius * 6);
  // front view from +Z, a little above: +X is to the right on screen
  camera.near = modelRadius / 50;
  camera.far = modelRadius * 200;
  const dist = modelRadius / Math.sin(THREE.MathUtils.degToRad(camera.fov / 2)) * 1.15;
  const elev = THREE.MathUtils.degToRad(15);
  camera.position.set(modelCentre.x, modelCentre.y + dist * Math.sin(elev), modelCentre.z + dist * Math.cos(elev));
  controls.target.copy(modelCentre);
  camera.updateProjectionMatrix();
  controls.update();
  const s = sun.shadow.camera;  // orthographic shadow frustum around the model and its shadow
  s.left = s.bottom = -modelRadius * 4;
  s.right = s.top = modelRadius * 4;
  s.near = modelRadius * 0.1;
  s.far = modelRadius * 20;
  s.updateProjectionMatrix();
}

function modelFailed(why) {
  state.errors.push("model: " + why);
  status.problem = "could not load the model (/model.glb): " + why;
  showStatus();
}
// fetched here rather than by GLTFLoader.load so that a refusal shows the server's reason (e.g. a
// broken --viewer-model file), not only its status code
fetch("/model.glb").then(async (r) => {
  if (!r.ok) throw new Error("HTTP " + r.status + ": " + (await r.text()).trim().slice(0, 300));
  return r.arrayBuffer();
}).then((buf) => new GLTFLoader().parse(buf, "", (gltf) => {
  gltf.scene.traverse((o) => {
    if (o.isMesh) { o.castShadow = true; o.receiveShadow = true; }
  });
  scene.add(gltf.scene);
  frameModel(gltf.scene);
  state.modelLoaded = true;
}, (err) => modelFailed(err.message || err))).catch((err) => modelFailed(err.message || err));

// ---- the estimate
function applyEstimate(est) {
  probe.sh.fromArray(est.sphericalHarmonicsCoefficients);
  probe.intensity = 1.0;
  const p = est.primaryLightIntensity;
  const scalar = Math.max(1.0, p.x, p.y, p.z);  // as XREstimatedLight: colour <= 1, the rest in intensity
  sun.color.setRGB(p.x / scalar, p.y / scalar, p.z / scalar);
  sun.intensity = est.hasPrimaryLight ? scalar : 0.0;
  const d = est.primaryLightDirection;
  const dir = new THREE.Vector3(d.x, d.y, d.z).normalize();
  sun.target.position.copy(modelCentre);
  sun.position.copy(modelCentre).addScaledVector(dir, modelRadius * 8);
  sun.target.updateMatrixWorld();
  if (withBackground) poseFromCamera(est);
  state.estimates += 1;
  state.frameId = est.frameId;
  state.last = est;
  if (showUi) {
    const amb = est.ambientIntensity.toFixed(3);
    const prim = est.hasPrimaryLight ? Math.max(p.x, p.y, p.z).toFixed(3) : "none";
    status.estimate = `frame ${est.frameId}  estimates ${state.estimates}  primary ${prim}  ambient ${amb}`;
    showStatus();
  }
}

// background=1: draw from the real camera's pose and intrinsics (OpenCV axes -> three.js axes)
const CV_TO_GL = new THREE.Matrix4().makeScale(1, -1, -1);
let bgAspect = null;
function poseFromCamera(est) {
  const T = est.coordinateFrame.T_cam_obj, K = est.camera;
  if (!T || !K) return;
  const camFromObj = new THREE.Matrix4().fromArray(T).transpose();  // row-major in the JSON
  const world = camFromObj.clone().invert().multiply(CV_TO_GL);
  camera.matrixAutoUpdate = false;
  camera.matrixWorld.copy(world);
  camera.matrixWorldInverse.copy(world).invert();
  const n = camera.near, f = camera.far, W = K.width, H = K.height;
  const cx = K.cx + 0.5, cy = K.cy + 0.5;  // OpenCV pixel centres are at integers
  camera.projectionMatrix.set(
    2 * K.fx / W, 0, 1 - 2 * cx / W, 0,
    0, 2 * K.fy / H, 2 * cy / H - 1, 0,
    0, 0, -(f + n) / (f - n), -2 * f * n / (f - n),
    0, 0, -1, 0);
  camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
  if (bgAspect !== W / H) { bgAspect = W / H; resize(); }
}

// The browser reconnects an event stream that drops by itself (after the server's "retry: 1000"), but
// gives up for good on an answer that is not a stream (503 when the server is busy, a proxy's error
// page): then reconnect here, waiting 1 s, 2 s ... up to 10 s. Either way the status line says so;
// the last figures would otherwise stay up as if live.
const RECONNECT_MS = 1000, RECONNECT_MAX_MS = 10000;
let reconnectMs = RECONNECT_MS;
state.reconnects = 0;
function connect() {
  const events = new EventSource("/estimates");
  events.onopen = () => {
    reconnectMs = RECONNECT_MS;
    status.connection = state.estimates === 0 ? "waiting for estimates…" : "";
    showStatus();
  };
  events.onmessage = (e) => {
    if (status.connection) { status.connection = ""; showStatus(); }
    try { applyEstimate(JSON.parse(e.data)); } catch (err) { state.errors.push("estimate: " + err); }
  };
  events.onerror = () => {
    if (events.readyState === EventSource.CLOSED) {
      events.close();
      status.connection = `no estimates: the server refused the connection; retrying in ${reconnectMs / 1000} s`;
      setTimeout(connect, reconnectMs);
      reconnectMs = Math.min(reconnectMs * 2, RECONNECT_MAX_MS);
      state.reconnects += 1;
    } else {
      status.connection = state.estimates === 0 ? "waiting for estimates…"
        : "the connection to the server is lost: the light is not live; reconnecting…";
    }
    showStatus();
  };
}
connect();

// ---- layout and render loop
function resize() {
  let w = window.innerWidth, h = window.innerHeight;
  if (bgAspect) {  // the picture's aspect, letterboxed (object-fit: contain), canvas exactly over it
    if (w / h > bgAspect) w = Math.round(h * bgAspect); else h = Math.round(w / bgAspect);
  }
  stage.style.width = w + "px";
  stage.style.height = h + "px";
  renderer.setSize(w, h, false);
  if (camera.matrixAutoUpdate) { camera.aspect = w / h; camera.updateProjectionMatrix(); }
}
window.addEventListener("resize", resize);
resize();

renderer.setAnimationLoop(() => {
  if (controls.enabled) controls.update();
  renderer.render(scene, camera);
  state.rendered += 1;
});
