// Load ?glb=URL with GLTFLoader, then report what three.js sees: morph targets per mesh, their
// names, the animation clips, and whether setting an influence and rendering a frame works.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";

function report(result) {
  window.t2bsResult = result;
  document.getElementById("out").textContent = JSON.stringify(result, null, 2);
}

const url = new URLSearchParams(window.location.search).get("glb");
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
      report({ ok: true, three: THREE.REVISION, meshes, clips, mixerOk });
    },
    undefined,
    (err) => report({ ok: false, error: String(err && err.message ? err.message : err) }),
  );
}
