// The KTX2 (Basis Universal) decoder behind pipeline25d.formats.ktx2: Binomial's transcoder as
// three.js ships it (WebAssembly), run by Node. Requests on stdin: u32 length + a KTX2 file.
// Replies on stdout: u32 status, width, height, alpha + the RGBA32 pixels of level 0, top row
// first; or status 1, the message's length, 0, 0 + the message (UTF-8).
"use strict";
const fs = require("fs");
const path = require("path");
const vm = require("vm");

const dir = process.argv[2];
const script = path.join(dir, "basis_transcoder.js");
// an Emscripten script that defines BASIS; three's package is an ES module one, so it is run here
const BASIS = vm.compileFunction(fs.readFileSync(script, "utf8") + "\nreturn BASIS;",
  ["require", "__filename", "__dirname"])(require, script, dir);

function transcode(basis, data) {
  const file = new basis.KTX2File(new Uint8Array(data));
  try {
    if (!file.isValid()) throw new Error("not a valid KTX2 file");
    if (!file.isETC1S() && !file.isUASTC()) throw new Error("its data is neither ETC1S nor UASTC");
    if (file.isHDR()) throw new Error("it is an HDR texture, which a map's 8-bit colour cannot hold");
    if (!file.startTranscoding()) throw new Error("its Basis Universal data cannot be transcoded");
    const fmt = basis.transcoder_texture_format.cTFRGBA32.value;
    const out = new Uint8Array(file.getImageTranscodedSizeInBytes(0, 0, 0, fmt));
    if (!file.transcodeImage(out, 0, 0, 0, fmt, 0, -1, -1)) throw new Error("transcoding failed");
    return [file.getWidth(), file.getHeight(), file.getHasAlpha() ? 1 : 0, out];
  } finally {
    file.close();
    file.delete();
  }
}

function reply(basis, data) {
  const head = Buffer.alloc(16);
  let body;
  try {
    const [w, h, alpha, pixels] = transcode(basis, data);
    head.writeUInt32LE(0, 0); head.writeUInt32LE(w, 4); head.writeUInt32LE(h, 8); head.writeUInt32LE(alpha, 12);
    body = Buffer.from(pixels.buffer, pixels.byteOffset, pixels.byteLength);
  } catch (e) {
    body = Buffer.from(String(e && e.message ? e.message : e), "utf8");
    head.writeUInt32LE(1, 0); head.writeUInt32LE(body.length, 4);
  }
  process.stdout.write(Buffer.concat([head, body]));
}

BASIS({ wasmBinary: fs.readFileSync(path.join(dir, "basis_transcoder.wasm")) }).then((basis) => {
  basis.initializeBasis();
  let pending = Buffer.alloc(0);
  process.stdin.on("data", (chunk) => {
    pending = pending.length ? Buffer.concat([pending, chunk]) : chunk;
    while (pending.length >= 4 && pending.length >= 4 + pending.readUInt32LE(0)) {
      const n = pending.readUInt32LE(0);
      reply(basis, pending.subarray(4, 4 + n));
      pending = pending.subarray(4 + n);
    }
  });
});
