// Load ?vrm=URL with GLTFLoader + three-vrm's VRMLoaderPlugin and report what three-vrm sees:
// meta, humanoid bones, the expression manager's expressions, and whether driving the "aa" and
// "blinkLeft" expressions moves the morph targets they are bound to.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { VRMLoaderPlugin } from "@pixiv/three-vrm";

function report(result) {
  window.t2bsResult = result;
  document.getElementById("out").textContent = JSON.stringify(result, null, 2);
}

const url = new URLSearchParams(window.location.search).get("vrm");
const loader = new GLTFLoader();
loader.register((parser) => new VRMLoaderPlugin(parser));
loader.load(
  url,
  (gltf) => {
    const vrm = gltf.userData.vrm;
    if (!vrm) {
      report({ ok: false, error: "three-vrm made no VRM from the file" });
      return;
    }
    let mesh = null;
    vrm.scene.traverse((o) => { if (o.isMesh && o.morphTargetInfluences) mesh = o; });
    const em = vrm.expressionManager;
    const driven = {};
    for (const name of ["aa", "blinkLeft", "jawOpen", "eyeBlinkLeft"]) {
      if (!em.getExpression(name)) continue;
      em.resetValues();
      em.setValue(name, 1.0);
      em.update();
      const moved = {};
      mesh.morphTargetInfluences.forEach((w, i) => { if (w > 0) moved[Object.keys(mesh.morphTargetDictionary).find((k) => mesh.morphTargetDictionary[k] === i)] = w; });
      driven[name] = moved;
    }
    em.resetValues();
    em.update();
    report({
      ok: true, three: THREE.REVISION,
      metaVersion: vrm.meta.metaVersion, name: vrm.meta.name, authors: vrm.meta.authors, licenseUrl: vrm.meta.licenseUrl,
      humanBones: Object.keys(vrm.humanoid.humanBones).filter((b) => vrm.humanoid.getRawBoneNode(b)),
      expressions: em.expressions.map((e) => e.expressionName),
      presets: Object.keys(em.presetExpressionMap),
      custom: Object.keys(em.customExpressionMap),
      driven,
    });
  },
  undefined,
  (err) => report({ ok: false, error: String(err && err.message ? err.message : err) }),
);
