// physmorph's offline 3D viewer of a morph's body (built by ../build.sh into ../../assets/viewer3d.js).
//
// window.PhysmorphViewer3D.mount(element, data) draws, in an orbitable WebGL view, the body's closed
// surface (a GLB per saved frame, one slider step each) on the left and the target's surface on the
// right, and optionally the last frame as 3D Gaussians (a 3DGS .ply drawn by Spark). Everything
// arrives as base64 strings in `data`: nothing is fetched, so the page works opened as file://.
//   data = {frames: [{frame, glb}], target: glb | null, splats: ply | null, label: string}
// It returns {ready, setFrame(i), showSplats(on)}: ready resolves once the first frame (and the
// target) is drawn, the two others once the view is redrawn. Failures (a bad GLB, no WebGL2) leave
// a one-line message in the element and reject `ready`; nothing is thrown to the page.
// Coordinates are the simulation's: domain [-16, 16]^3, +y up.

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { SparkRenderer, SplatMesh, SplatFileType } from "@sparkjsdev/spark";

const BACKGROUND = 0xf4f4f4;
const BODY_COLOUR = 0xd9895b; // warm
const TARGET_COLOUR = 0x5f8fc4; // cool
const ASPECT = 9 / 16; // canvas height / width
const DEFAULT_WIDTH = 640;
const SPREAD = 0.6; // body and target at -/+ SPREAD x the larger bounding-box width
const FOV = 35; // vertical, degrees
const SPLAT_WAIT_FRAMES = 600; // at most this many redraws waiting for Spark's sorted splats

function bytesFromBase64(text) {
  if (typeof text !== "string" || text.length === 0) throw new Error("empty base64 data");
  const clean = text.replace(/\s+/g, "");
  if (typeof Uint8Array.fromBase64 === "function") return Uint8Array.fromBase64(clean);
  const binary = atob(clean);
  const out = new Uint8Array(binary.length);
  for (let i = 0; i < binary.length; i++) out[i] = binary.charCodeAt(i);
  return out;
}

function hasWebGL2() {
  try {
    const probe = document.createElement("canvas");
    const gl = probe.getContext("webgl2");
    if (!gl) return false;
    const lose = gl.getExtension("WEBGL_lose_context");
    if (lose) lose.loseContext();
    return true;
  } catch (e) {
    return false;
  }
}

function message(err) {
  const text = err && err.message ? err.message : String(err);
  return text.split("\n")[0];
}

// A GLB's meshes in one group, drawn with `material` (the file's own materials are dropped).
async function parseSurface(loader, base64, material, what) {
  let gltf;
  try {
    const bytes = bytesFromBase64(base64);
    const buffer = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
    gltf = await loader.parseAsync(buffer, "");
  } catch (err) {
    throw new Error(`${what}: not a readable GLB (${message(err)})`);
  }
  const group = new THREE.Group();
  const meshes = [];
  gltf.scene.updateMatrixWorld(true);
  gltf.scene.traverse((node) => {
    if (node.isMesh) meshes.push(node);
  });
  if (meshes.length === 0) throw new Error(`${what}: the GLB holds no mesh`);
  for (const node of meshes) {
    const geometry = node.geometry.clone();
    geometry.applyMatrix4(node.matrixWorld); // bake the file's node transforms
    if (!geometry.getAttribute("normal")) geometry.computeVertexNormals();
    geometry.computeBoundingBox();
    group.add(new THREE.Mesh(geometry, material));
  }
  return group;
}

function boxOf(object) {
  return new THREE.Box3().setFromObject(object);
}

function mount(element, data) {
  let resolveReady;
  let rejectReady;
  const ready = new Promise((resolve, reject) => {
    resolveReady = resolve;
    rejectReady = reject;
  });
  ready.catch(() => {}); // a caller that ignores `ready` gets no unhandled rejection

  const state = { failed: false };
  const fail = (err) => {
    if (state.failed) return;
    state.failed = true;
    const line = `3D view unavailable: ${message(err)}`;
    try {
      element.replaceChildren();
      const p = document.createElement("p");
      p.className = "viewer3d-error";
      p.textContent = line;
      element.appendChild(p);
    } catch (e) {
      /* the element itself is unusable: nothing more to show */
    }
    rejectReady(new Error(line));
  };

  const inner = {
    setFrame: () => Promise.reject(new Error("3D view not built")),
    showSplats: () => Promise.reject(new Error("3D view not built")),
  };
  try {
    build(element, data, inner, resolveReady, fail, state);
  } catch (err) {
    fail(err);
  }
  const guard = (name) => (arg) => {
    let out;
    try {
      out = state.failed ? Promise.reject(new Error("3D view failed")) : inner[name](arg);
    } catch (err) {
      out = Promise.reject(err);
    }
    out.catch(() => {});
    return out;
  };
  return { ready, setFrame: guard("setFrame"), showSplats: guard("showSplats") };
}

function build(element, data, api, resolveReady, fail, state) {
  if (!element || typeof element.appendChild !== "function") throw new Error("no element to mount in");
  if (!data || !Array.isArray(data.frames) || data.frames.length === 0) throw new Error("no frames to show");
  const frames = data.frames;
  const last = frames.length - 1;
  if (!hasWebGL2()) throw new Error("this browser has no WebGL2");

  // --- the DOM: canvas, slider + label (+ splats switch), caption
  element.replaceChildren();
  const root = document.createElement("div");
  root.className = "viewer3d";
  const canvas = document.createElement("canvas");
  canvas.style.display = "block";
  const bar = document.createElement("div");
  bar.className = "viewer3d-controls";
  bar.style.cssText = "display:flex;align-items:center;gap:0.6em;margin-top:0.3em;";
  const slider = document.createElement("input");
  slider.type = "range";
  slider.className = "frame3d";
  slider.min = "0";
  slider.max = String(last);
  slider.step = "1";
  slider.value = String(last);
  slider.style.flex = "1";
  slider.disabled = frames.length < 2;
  const label = document.createElement("span");
  label.className = "frame3d-label";
  label.textContent = `frame ${frames[last].frame}`;
  bar.append(slider, label);
  let splatBox = null;
  if (data.splats) {
    const wrap = document.createElement("label");
    wrap.className = "viewer3d-splats";
    splatBox = document.createElement("input");
    splatBox.type = "checkbox";
    splatBox.className = "splats3d";
    splatBox.disabled = true; // enabled once the splats are decoded
    wrap.append(splatBox, document.createTextNode(" splats (last frame)"));
    bar.append(wrap);
  }
  const caption = document.createElement("div");
  caption.className = "viewer3d-caption";
  caption.textContent = data.label == null ? "" : String(data.label);
  root.append(canvas, bar, caption);
  element.appendChild(root);

  // --- renderer, scene, camera, lights
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
  canvas.addEventListener("webglcontextlost", (event) => {
    event.preventDefault();
    fail(new Error("the WebGL context was lost"));
  });
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(BACKGROUND);
  const camera = new THREE.PerspectiveCamera(FOV, 1 / ASPECT, 0.1, 1000);
  scene.add(camera);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x8a8580, 1.6));
  const sun = new THREE.DirectionalLight(0xffffff, 2.0);
  sun.position.set(0.5, 1.0, 0.8); // in the camera's frame: the light follows the view
  sun.target.position.set(0, 0, -1);
  camera.add(sun, sun.target);

  const surfaceMaterial = (colour) =>
    new THREE.MeshStandardMaterial({ color: colour, roughness: 0.6, metalness: 0.0, side: THREE.DoubleSide });
  const bodyMaterial = surfaceMaterial(BODY_COLOUR);
  const targetMaterial = surfaceMaterial(TARGET_COLOUR);
  const bodySlot = new THREE.Group(); // the shown frame's surface (or the splats), on the left
  const targetSlot = new THREE.Group();
  scene.add(bodySlot, targetSlot);

  const controls = new OrbitControls(camera, canvas);
  controls.enableDamping = true;
  controls.dampingFactor = 0.12;

  // --- drawing on demand: a frame per request, more while the controls damp or Spark sorts
  let spark = null;
  let splatMesh = null;
  let pending = null; // {promise, resolve}: the next complete redraw
  let scheduled = false;
  let splatWait = 0;
  // Spark sorts in its worker: a redraw is complete once the sorted splats (or none, when hidden) show
  const splatsSettled = () =>
    !spark || (!spark.sorting && !spark.sortDirty &&
      (splatMesh && splatMesh.visible ? spark.activeSplats > 0 : spark.activeSplats === 0));
  const request = () => {
    if (!scheduled && !state.failed) {
      scheduled = true;
      requestAnimationFrame(draw);
    }
  };
  function draw() {
    scheduled = false;
    if (state.failed) return;
    let again = false;
    try {
      // the controls move the camera only while they report changes: the sub-threshold tail of their
      // damping would otherwise nudge it on every later frame, and any move makes Spark re-sort
      if (controlsMoving) {
        if (controls.update()) again = true;
        else controlsMoving = false;
      }
      renderer.render(scene, camera);
    } catch (err) {
      fail(err);
      return;
    }
    if (pending && !splatsSettled() && splatWait < SPLAT_WAIT_FRAMES) {
      splatWait += 1;
      again = true;
    } else if (pending) {
      const done = pending;
      pending = null;
      done.resolve();
    }
    if (again) request();
  }
  const redraw = () => {
    splatWait = 0;
    if (!pending) {
      let resolve;
      const promise = new Promise((r) => {
        resolve = r;
      });
      pending = { promise, resolve };
    }
    request();
    return pending.promise;
  };
  let controlsMoving = false;
  const onControls = () => {
    controlsMoving = true;
    request();
  };
  controls.addEventListener("start", onControls);
  controls.addEventListener("change", onControls);

  const resize = () => {
    const width = Math.max(1, Math.round(element.clientWidth || DEFAULT_WIDTH));
    const height = Math.max(1, Math.round(width * ASPECT));
    const size = renderer.getSize(new THREE.Vector2());
    if (size.x === width && size.y === height) return;
    renderer.setSize(width, height);
    camera.aspect = width / height;
    camera.updateProjectionMatrix();
    request();
  };
  resize();
  if (typeof ResizeObserver === "function") new ResizeObserver(resize).observe(element);
  else window.addEventListener("resize", resize);

  // --- the surfaces: parsed on demand; placed once, from the first and last frames and the target
  const loader = new GLTFLoader();
  const parsed = new Map(); // frame index -> Promise<Group>
  const surface = (i) => {
    if (!parsed.has(i)) {
      const entry = frames[i];
      const what = `frame ${entry && entry.frame != null ? entry.frame : i}`;
      const p = parseSurface(loader, entry && entry.glb, bodyMaterial, what);
      parsed.set(i, p);
      p.catch(() => parsed.delete(i));
    }
    return parsed.get(i);
  };
  let shown = -1;
  let splatsOn = false;

  const place = (bodyBox, targetBox) => {
    const centre = new THREE.Vector3();
    let width = bodyBox.getSize(new THREE.Vector3()).x;
    if (targetBox) width = Math.max(width, targetBox.getSize(new THREE.Vector3()).x);
    const shift = targetBox ? SPREAD * Math.max(width, 1e-6) : 0;
    bodyBox.getCenter(centre);
    bodySlot.position.set(-shift - centre.x, -centre.y, -centre.z);
    if (targetBox) {
      targetBox.getCenter(centre);
      targetSlot.position.set(shift - centre.x, -centre.y, -centre.z);
    }
  };

  // the camera in front of (and a little above) `box`, the placed surfaces' box in world coordinates
  const fitCamera = (box) => {
    if (box.isEmpty()) box.set(new THREE.Vector3(-16, -16, -16), new THREE.Vector3(16, 16, 16));
    const sphere = box.getBoundingSphere(new THREE.Sphere());
    const radius = Math.max(sphere.radius, 1e-3);
    const half = box.getSize(new THREE.Vector3()).multiplyScalar(0.5).max(new THREE.Vector3(1e-3, 1e-3, 1e-3));
    const tanV = Math.tan(THREE.MathUtils.degToRad(FOV) / 2);
    const tanH = tanV * camera.aspect;
    // the box's front face fills the view, with a margin
    const distance = 1.15 * (Math.max(half.x / tanH, half.y / tanV) + half.z);
    const direction = new THREE.Vector3(0.0, 0.28, 1.0).normalize();
    camera.position.copy(sphere.center).addScaledVector(direction, distance);
    camera.near = Math.max(distance - 4 * radius, distance / 100);
    camera.far = distance + 4 * radius;
    camera.updateProjectionMatrix();
    controls.target.copy(sphere.center);
    controls.minDistance = radius * 0.2;
    controls.maxDistance = distance * 5;
    controls.update();
  };

  const display = (i) => {
    label.textContent = `frame ${frames[i].frame}`;
    slider.value = String(i);
    return surface(i).then((group) => {
      for (const child of [...bodySlot.children]) if (child !== splatMesh) bodySlot.remove(child);
      group.visible = !splatsOn;
      bodySlot.add(group);
      shown = i;
    });
  };

  // changes run one at a time, in order; `queue` itself never rejects, so later changes still run
  let queue = Promise.resolve();
  const enqueue = (step) => {
    const run = queue.then(step);
    queue = run.catch(() => {});
    return run;
  };

  let wantedFrame = last;
  const setFrame = (i) => {
    const wanted = Math.round(Number(i));
    if (!Number.isFinite(wanted)) return Promise.reject(new Error(`bad frame index ${i}`));
    const index = Math.max(0, Math.min(last, wanted));
    if (splatsOn && index !== last) return Promise.reject(new Error("the splats show the last frame only"));
    wantedFrame = index;
    // a later request (a dragged slider) supersedes this one before it is drawn
    const run = enqueue(() => (index === wantedFrame ? display(index).then(redraw) : undefined));
    run.catch((err) => {
      label.textContent = `frame ${frames[index].frame}: ${message(err)}`;
    });
    return run;
  };
  slider.addEventListener("input", () => {
    setFrame(Number(slider.value)).catch(() => {});
  });

  // --- first draw: the last frame (with the first, for the layout) and the target
  const targetPromise = data.target
    ? parseSurface(loader, data.target, targetMaterial, "target")
    : Promise.resolve(null);
  const firstDrawn = Promise.all([surface(last), targetPromise, last > 0 ? surface(0) : null]).then(
    ([lastGroup, targetGroup, firstGroup]) => {
      const bodyBox = boxOf(lastGroup);
      if (firstGroup) bodyBox.union(boxOf(firstGroup));
      const targetBox = targetGroup ? boxOf(targetGroup) : null;
      place(bodyBox, targetBox);
      if (targetGroup) targetSlot.add(targetGroup);
      bodySlot.add(lastGroup);
      shown = last;
      const world = bodyBox.clone().translate(bodySlot.position);
      if (targetBox) world.union(targetBox.clone().translate(targetSlot.position));
      fitCamera(world);
      return redraw();
    },
  );
  queue = firstDrawn.catch(() => {});
  firstDrawn.then(() => resolveReady(), fail);

  // --- the splats: decoded by Spark (its worker and wasm are inlined) after the first draw
  const splatsLoaded = !data.splats
    ? Promise.reject(new Error("this view has no splats"))
    : firstDrawn.then(async () => {
      spark = new SparkRenderer({ renderer, onDirty: request });
      scene.add(spark);
      const mesh = new SplatMesh({ fileBytes: bytesFromBase64(data.splats), fileType: SplatFileType.PLY });
      try {
        await mesh.initialized;
      } catch (err) {
        throw new Error(`splats: ${message(err)}`); // Spark's worker rejects with a bare reason
      }
      mesh.visible = splatsOn;
      splatMesh = mesh;
      bodySlot.add(mesh);
      splatBox.disabled = false;
    });
  splatsLoaded.catch((err) => {
    if (!splatBox || state.failed) return;
    splatBox.disabled = true;
    splatBox.title = `unavailable: ${message(err)}`;
    console.warn(`physmorph viewer3d: ${message(err)}`);
  });

  const showSplats = (on) => {
    const want = Boolean(on);
    if (!splatBox) return want ? Promise.reject(new Error("this view has no splats")) : redraw();
    splatBox.checked = want;
    const run = enqueue(() => {
      if (!want) {
        splatsOn = false;
        for (const child of bodySlot.children) child.visible = child !== splatMesh;
        slider.disabled = frames.length < 2;
        return redraw();
      }
      return splatsLoaded
        .then(() => {
          wantedFrame = last;
          return shown === last ? null : display(last);
        })
        .then(() => {
          splatsOn = true;
          slider.disabled = true; // the splats are the last frame's
          for (const child of bodySlot.children) child.visible = child === splatMesh;
          return redraw();
        });
    });
    run.catch(() => {
      splatBox.checked = splatsOn;
    });
    return run;
  };
  if (splatBox) {
    splatBox.addEventListener("change", () => {
      showSplats(splatBox.checked).catch(() => {});
    });
  }

  api.setFrame = setFrame;
  api.showSplats = showSplats;
}

window.PhysmorphViewer3D = { mount };
