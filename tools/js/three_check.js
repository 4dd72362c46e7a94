// Load ?glb=URL with GLTFLoader, then report what three.js sees: morph targets per mesh, their
// names, the animation clips, and whether setting an influence and rendering a frame works.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";

function report(result) {
  window.t2bsResult = result;
  document.getElementById("out").textContent = JSON.stringify(result, null, 2);
}

const params = new URLSearchParams(window.location.search);
const url = params.get("glb");

function safeScreenshots(gltf, name) {
  try {
    return screenshots(gltf, name);
  } catch (err) {
    return { error: `WebGL screenshots failed: ${err && err.message ? err.message : err}` };
  }
}
const shot = params.get("shot"); // a morph target name: render it at weight 0 and 1 (WebGL screenshots)

// Frontal screenshots of the first morphing mesh with target ``name`` at 0 and at 1: the pipeline's
// frontal camera (fov 30, distance 2.25, canonical frame), a key light + ambient, 256 px.
function screenshots(gltf, name) {
  let mesh = null;
  gltf.scene.traverse((o) => { if (o.isMesh && o.morphTargetDictionary && name in o.morphTargetDictionary) mesh = o; });
  if (!mesh) return { error: `no morph target ${name}` };
  const size = 256;
  const renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
  renderer.setSize(size, size);
  renderer.setClearColor(0xffffff, 1);
  const scene = new THREE.Scene();
  scene.add(gltf.scene);
  scene.add(new THREE.AmbientLight(0xffffff, 1.2));
  const key = new THREE.DirectionalLight(0xffffff, 2.0);
  key.position.set(0.5, 1.0, 2.0);
  scene.add(key);
  const camera = new THREE.PerspectiveCamera(30, 1, 0.1, 10);
  camera.position.set(0, 0, 2.25);
  camera.lookAt(0, 0, 0);
  const out = {};
  const pixels = {};
  for (const w of [0, 1]) {
    mesh.morphTargetInfluences.fill(0);
    mesh.morphTargetInfluences[mesh.morphTargetDictionary[name]] = w;
    renderer.render(scene, camera);
    out[w] = renderer.domElement.toDataURL("image/png");
    const gl = renderer.getContext();
    const buf = new Uint8Array(size * size * 4);
    gl.readPixels(0, 0, size, size, gl.RGBA, gl.UNSIGNED_BYTE, buf);
    pixels[w] = buf;
  }
  let changed = 0;
  for (let i = 0; i < size * size; i++) {
    const d = Math.abs(pixels[0][4 * i] - pixels[1][4 * i]) + Math.abs(pixels[0][4 * i + 1] - pixels[1][4 * i + 1]) + Math.abs(pixels[0][4 * i + 2] - pixels[1][4 * i + 2]);
    if (d > 30) changed++;
  }
  let drawn = 0;
  for (let i = 0; i < size * size; i++) if (pixels[0][4 * i] + pixels[0][4 * i + 1] + pixels[0][4 * i + 2] < 750) drawn++;
  return { name, size, neutral: out[0], posed: out[1], changedPixels: changed, characterPixels: drawn };
}
if (!url) {
  report({ ok: false, error: "no ?glb= given" });
} else {
  new GLTFLoader().load(
    url,
    (gltf) => {
      const meshes = [];
      gltf.scene.traverse((obj) => {
        if (obj.isMesh) {
          meshes.push({
            name: obj.name,
            vertices: obj.geometry.attributes.position.count,
            morphTargetInfluences: obj.morphTargetInfluences ? obj.morphTargetInfluences.length : 0,
            influencesAllZero: obj.morphTargetInfluences ? obj.morphTargetInfluences.every((w) => w === 0) : true,
            morphPositions: obj.geometry.morphAttributes.position ? obj.geometry.morphAttributes.position.length : 0,
            targetNames: obj.morphTargetDictionary ? Object.keys(obj.morphTargetDictionary) : [],
            textured: !!(obj.material && obj.material.map),
          });
        }
      });
      const clips = gltf.animations.map((c) => ({ name: c.name, duration: c.duration, tracks: c.tracks.length }));
      // Drive one influence and step the animation mixer: exercises the morph path of the loader.
      let mixerOk = null;
      try {
        const mixer = new THREE.AnimationMixer(gltf.scene);
        if (gltf.animations.length) mixer.clipAction(gltf.animations[0]).play();
        mixer.update(0.25);
        mixerOk = true;
      } catch (err) {
        mixerOk = String(err);
      }
      const dictionaries = meshes.map((m) => m.targetNames);
      report({ ok: true, three: THREE.REVISION, meshes, clips, mixerOk, dictionaries,
               screenshots: shot ? safeScreenshots(gltf, shot) : null });
    },
    undefined,
    (err) => report({ ok: false, error: String(err && err.message ? err.message : err) }),
  );
}
