// Loads a .glb with three.js's GLTFLoader, plays its first animation clip with an AnimationMixer
// and reports where three.js puts every vertex of every mesh at each time: morph targets and
// skinning applied (getVertexPosition), then the mesh's world matrix, as three.js draws them.
// Bundled by tests/test_avatar_video.py with esbuild; the page calls window.poseGlb(bytes, times).
import { AnimationMixer, Vector3 } from "three";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";

window.poseGlb = async (bytes, times) => {
  const gltf = await new GLTFLoader().parseAsync(new Uint8Array(bytes).buffer, "");
  const mixer = new AnimationMixer(gltf.scene);
  mixer.clipAction(gltf.animations[0]).play();
  const meshes = [];
  gltf.scene.traverse((o) => {
    if (o.isMesh) meshes.push(o);
  });
  const frames = [];
  let now = 0;
  const v = new Vector3();
  for (const t of times) {
    mixer.update(t - now);
    now = t;
    gltf.scene.updateMatrixWorld(true);
    const points = [];
    for (const mesh of meshes) {
      if (mesh.isSkinnedMesh) mesh.skeleton.update();
      const count = mesh.geometry.attributes.position.count;
      for (let i = 0; i < count; i++) {
        mesh.getVertexPosition(i, v);
        v.applyMatrix4(mesh.matrixWorld);
        points.push(v.x, v.y, v.z);
      }
    }
    frames.push(points);
  }
  return { clip: gltf.animations[0].name, frames };
};
