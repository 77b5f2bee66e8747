// talkmesh-client's example: the server's bundled head (GET /head.glb) in a three.js scene,
// animated by a speech file streamed through TalkmeshClient, in step with its audio, or by the
// microphone, live. Served by
// `talkmesh serve` itself, so the page and the stream share an origin.

import * as THREE from "three";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";
import { TalkmeshClient } from "../index.js";

const renderer = new THREE.WebGLRenderer({ antialias: true });
renderer.setSize(innerWidth, innerHeight);
document.body.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x202428);
scene.add(new THREE.HemisphereLight(0xffffff, 0x404040, 2.5));
const camera = new THREE.PerspectiveCamera(30, innerWidth / innerHeight, 0.01, 10);
camera.position.set(0, 0, 0.6);

const url = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws/stream`;
const client = new TalkmeshClient(url);
const status = document.getElementById("status");
// what the page showed, for tests: the head's jawOpen influence at every frame shown
window.example = { client, jaw: [], ready: false, error: null };

new GLTFLoader().load("/head.glb", (gltf) => {
  scene.add(gltf.scene);
  const box = new THREE.Box3().setFromObject(gltf.scene);
  camera.lookAt(box.getCenter(new THREE.Vector3()));
  const driven = client.attach(gltf.scene);
  status.textContent = `${driven} morph targets driven; load a speech file`;
  let jaw = null;
  gltf.scene.traverse((o) => {
    if (o.morphTargetDictionary && o.morphTargetDictionary.jawOpen !== undefined) jaw = o;
  });
  client.onframe = () => window.example.jaw.push(jaw.morphTargetInfluences[jaw.morphTargetDictionary.jawOpen]);
  window.example.ready = true;
});

document.getElementById("file").addEventListener("change", async (event) => {
  const file = event.target.files[0];
  try {
    await client.context.resume();
    const buffer = await client.context.decodeAudioData(await file.arrayBuffer());
    status.textContent = `streaming ${file.name}`;
    const frames = await client.playAudio(buffer);
    status.textContent = `${frames} frames`;
  } catch (e) {
    window.example.error = String(e.message || e);
    status.textContent = window.example.error;
  }
});

document.getElementById("mic").addEventListener("click", async () => {
  window.example.error = null;
  document.getElementById("stop").disabled = false;
  try {
    status.textContent = "streaming the microphone";
    const frames = await client.streamMicrophone();
    status.textContent = `${frames} frames`;
  } catch (e) {
    window.example.error = String(e.message || e);
    status.textContent = window.example.error;
  }
  document.getElementById("stop").disabled = true;
});
document.getElementById("stop").addEventListener("click", () => client.stopMicrophone());

renderer.setAnimationLoop(() => {
  client.update();
  renderer.render(scene, camera);
});
