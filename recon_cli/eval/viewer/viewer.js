// recon view: the page's own script, over RECON3 (the three.js bundle inlined before it).
// The first view is recon's rasteriser's camera (recon_cli/eval/render.py): orthographic, y up,
// the frame's sphere over 92 % of the canvas's smaller side, flat two-sided Lambert shading under
// a headlight. Tests wait on window.reconReady (or window.reconError); window.reconFirstFrameMs is
// the time of the first frame since the navigation started, window.reconTimes the script's start,
// the geometry decoded and the first animation frame after the first frame.
window.addEventListener("error", (e) => {
  window.reconError = String(e.message);
});
(function () {
  "use strict";
  const T = window.RECON3;
  window.reconTimes = { start: performance.now() };
  const meta = JSON.parse(document.getElementById("recon-meta").textContent);
  const holder = document.getElementById("view");
  const message = document.getElementById("message");
  const FILL = 0.46; // the frame's radius over the smaller side (render.py: 0.46 * min(w, h))
  const BASE = [0.74, 0.76, 0.8]; // render.py's BASE_COLOR
  const AMBIENT = 0.22; // render.py's _AMBIENT
  const CLOUD_SHADE = 0.8; // render.py shades a cloud without normals at 0.8
  const R = meta.radius;

  function fail(text) {
    message.textContent = text;
    window.reconError = text;
  }

  function bytes(id) {
    const text = document.getElementById(id).textContent;
    if (typeof Uint8Array.fromBase64 === "function") return Uint8Array.fromBase64(text);
    const bin = atob(text);
    const out = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
    return out;
  }

  function typed(Kind, id) {
    const b = bytes(id);
    return new Kind(b.buffer, b.byteOffset, b.byteLength / Kind.BYTES_PER_ELEMENT);
  }

  // a heatmap's colour under the rasteriser's shading of heatmaps: colour * (0.55 + 0.45 shade)
  const HEAT = (shade) => `(0.55 + 0.45 * ${shade})`;
  const k = Math.hypot(0.3, 0.45, 1.0);
  const HEADLIGHT = `vec3(${0.3 / k}, ${0.45 / k}, ${1.0 / k})`; // in the camera's frame

  // round points (discs of the rasteriser's radius, not squares), shaded as the rasteriser
  // shades them: ambient + (1 - ambient) |n . headlight| with normals, 0.8 without (file
  // colours without normals are shown as they are)
  function pointShader(shader, layer) {
    let shade = "vShade = " + (layer.colors !== null && !layer.heat ? "1.0" : String(CLOUD_SHADE)) + ";";
    if (layer.normals !== null) {
      shade = `vec3 n = normalMatrix * normal;
  float len = length(n);
  vShade = len > 0.0 ? ${AMBIENT} + ${1 - AMBIENT} * abs(dot(n / len, ${HEADLIGHT})) : ${CLOUD_SHADE};`;
    }
    const factor = layer.heat ? HEAT("vShade") : "vShade";
    shader.vertexShader = ("varying float vShade;\n" + shader.vertexShader).replace(
      "#include <color_vertex>",
      `#include <color_vertex>\n  ${shade}`,
    );
    shader.fragmentShader = ("varying float vShade;\n" + shader.fragmentShader)
      .replace("void main() {", "void main() {\n  if (length(gl_PointCoord - 0.5) > 0.5) discard;")
      .replace("#include <color_fragment>", `#include <color_fragment>\n  diffuseColor.rgb *= ${factor};`);
  }

  // three's Lambert with the scene's lights gives ambient + (1 - ambient) cos; a heatmap keeps
  // more of its colour
  function heatShader(shader) {
    const lit = "(reflectedLight.directDiffuse + reflectedLight.indirectDiffuse)";
    shader.fragmentShader = shader.fragmentShader.replace(
      "vec3 outgoingLight = reflectedLight.directDiffuse + reflectedLight.indirectDiffuse",
      `vec3 outgoingLight = 0.55 * diffuseColor.rgb + 0.45 * ${lit}`,
    );
  }

  function makeObject(layer) {
    const g = new T.BufferGeometry();
    g.setAttribute("position", new T.BufferAttribute(typed(Float32Array, layer.positions), 3));
    const colored = layer.colors !== null;
    if (colored) g.setAttribute("color", new T.BufferAttribute(bytes(layer.colors), 3, true));
    const color = colored ? new T.Color(1, 1, 1) : new T.Color(BASE[0], BASE[1], BASE[2]);
    let obj;
    if (layer.faces !== null) {
      const Index = layer.index === "uint32" ? Uint32Array : Uint16Array;
      g.setIndex(new T.BufferAttribute(typed(Index, layer.faces), 1));
      const material = new T.MeshLambertMaterial({
        color,
        vertexColors: colored,
        side: T.DoubleSide,
        flatShading: true,
      });
      if (layer.heat) material.onBeforeCompile = heatShader;
      obj = new T.Mesh(g, material);
    } else {
      if (layer.normals !== null) {
        g.setAttribute("normal", new T.BufferAttribute(typed(Int8Array, layer.normals), 3, true));
      }
      const material = new T.PointsMaterial({ color, vertexColors: colored, sizeAttenuation: false });
      material.onBeforeCompile = (shader) => pointShader(shader, layer);
      obj = new T.Points(g, material);
    }
    obj.frustumCulled = false; // the frame holds every layer: no bounding sphere to compute
    obj.visible = layer.visible;
    return obj;
  }

  T.ColorManagement.enabled = false; // colours are used as given, as the rasteriser does
  let renderer;
  try {
    renderer = new T.WebGLRenderer({ antialias: meta.antialias });
  } catch (e) {
    fail("WebGL is not available in this browser: " + e.message);
    return;
  }
  renderer.outputColorSpace = T.LinearSRGBColorSpace;
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  renderer.setClearColor(0xffffff, 1);
  holder.appendChild(renderer.domElement);

  const scene = new T.Scene();
  const camera = new T.OrthographicCamera(-1, 1, 1, -1, 2 * R, 6 * R);
  scene.add(camera);
  // three's Lambert divides by pi: these intensities give ambient + (1 - ambient) cos
  scene.add(new T.AmbientLight(0xffffff, AMBIENT * Math.PI));
  const light = new T.DirectionalLight(0xffffff, (1 - AMBIENT) * Math.PI);
  light.position.set(0.3, 0.45, 1.0); // the rasteriser's headlight, raised and moved right a little
  light.target = camera;
  camera.add(light);

  let objects;
  try {
    objects = meta.layers.map(makeObject);
  } catch (e) {
    fail("cannot read the geometry of this page: " + e.message);
    return;
  }
  for (const obj of objects) scene.add(obj);
  window.reconTimes.decoded = performance.now();

  function draw() {
    renderer.render(scene, camera);
  }

  const controls = new T.OrbitControls(camera, renderer.domElement);
  controls.addEventListener("change", draw);

  function fit() {
    const w = Math.max(1, Math.floor(holder.clientWidth));
    const h = Math.max(1, Math.floor(holder.clientHeight));
    renderer.setSize(w, h);
    const s = (FILL * Math.min(w, h)) / R; // pixels per world unit
    camera.left = -w / 2 / s;
    camera.right = w / 2 / s;
    camera.top = h / 2 / s;
    camera.bottom = -h / 2 / s;
    camera.updateProjectionMatrix();
    const size = 2 * Math.max(1, w / 250); // the rasteriser's disc radius: width / 250, at least 1
    for (const obj of objects) if (obj.isPoints) obj.material.size = size;
  }

  // back: the unit vector from the centre towards the camera (render.camera's third row)
  function lookFrom(back) {
    const d = 4 * R;
    camera.up.set(0, 1, 0);
    camera.position.set(back[0] * d, back[1] * d, back[2] * d);
    camera.zoom = 1;
    camera.lookAt(0, 0, 0);
    camera.updateProjectionMatrix();
    controls.target.set(0, 0, 0);
    controls.update();
    draw();
  }

  function setView(name) {
    lookFrom(name === "reset" ? meta.view : meta.views[name]);
  }

  for (const b of document.querySelectorAll("#views button")) {
    b.addEventListener("click", () => setView(b.dataset.view));
  }
  for (const c of document.querySelectorAll("#layers input")) {
    c.addEventListener("change", () => {
      objects[Number(c.dataset.layer)].visible = c.checked;
      draw();
    });
  }

  fit();
  lookFrom(meta.view);
  // reading a pixel waits until the GPU has drawn the frame (finish() does not wait in Chrome)
  const gl = renderer.getContext();
  gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4));
  const ms = performance.now();
  window.reconFirstFrameMs = ms;
  document.getElementById("timing").textContent = `first frame ${(ms / 1000).toFixed(2)} s after opening`;
  window.recon = { setView, draw, meta };
  new ResizeObserver(() => {
    fit();
    draw();
  }).observe(holder);
  requestAnimationFrame(() => {
    window.reconTimes.raf = performance.now();
    window.reconReady = true;
  });
})();
