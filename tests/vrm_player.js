// Loads a .vrm with three.js's GLTFLoader and @pixiv/three-vrm (the VRM loader most web apps use),
// plays its first animation clip with an AnimationMixer and reports what the VRM runtime sees:
// the VRM version, its expression presets, and each mesh's morph target weights over the clip.
// Each step updates the VRM first (its expression manager resets the morph targets its presets
// bind) and the mixer after it, so that the clip's weights are the ones drawn.
// Bundled by tests/test_browser_vrm.py with esbuild; the page calls window.playVrm(bytes, times).
import { AnimationMixer } from "three";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";
import { VRMLoaderPlugin } from "@pixiv/three-vrm";

window.playVrm = async (bytes, times) => {
  const loader = new GLTFLoader();
  loader.register((parser) => new VRMLoaderPlugin(parser));
  const gltf = await loader.parseAsync(new Uint8Array(bytes).buffer, "");
  const vrm = gltf.userData.vrm;
  const clip = gltf.animations[0];
  const mixer = new AnimationMixer(gltf.scene);
  mixer.clipAction(clip).play();
  const meshes = [];
  gltf.scene.traverse((o) => {
    if (o.isMesh && o.morphTargetInfluences) meshes.push(o);
  });
  const frames = [];
  let now = 0;
  for (const t of times) {
    if (vrm) vrm.update(t - now);
    mixer.update(t - now);
    now = t;
    frames.push(meshes.map((m) => Array.from(m.morphTargetInfluences)));
  }
  return {
    version: vrm ? vrm.meta.metaVersion : null,
    presets: vrm && vrm.expressionManager ? Object.keys(vrm.expressionManager.presetExpressionMap) : [],
    clips: gltf.animations.map((a) => a.name),
    meshes: meshes.map((m) => m.name),
    frames,
  };
};
