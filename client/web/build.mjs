// Builds the browser spectator into server/static, the files `posecast serve` sends:
// app-HASH.js, app-HASH.css and network-HASH.js (the page's websocket worker), named by
// a hash of their content so the server can let browsers cache them for good;
// index.html, which names them; licenses.txt, the notices of the packages bundled.
// Run by `make setup` (after npm ci).
import { build } from "esbuild";
import { mkdir, readdir, readFile, rm, writeFile } from "node:fs/promises";
import { basename, dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

const here = dirname(fileURLToPath(import.meta.url));
const out = join(here, "..", "..", "server", "static");

await mkdir(out, { recursive: true });
for (const name of await readdir(out)) {
  if (/^(app|network)-/.test(name) || ["index.html", "licenses.txt"].includes(name)) {
    await rm(join(out, name));
  }
}
const result = await build({
  entryPoints: { app: join(here, "src", "main.js"), network: join(here, "src", "network.js") },
  bundle: true, minify: true, format: "esm", target: "es2020",
  outdir: out, entryNames: "[name]-[hash]", metafile: true, logLevel: "warning",
  legalComments: "none", // every bundled package's whole notice is in licenses.txt
  banner: { js: "/*! posecast browser spectator; bundled packages' licences: /static/licenses.txt */" },
});
const packages = new Set(Object.keys(result.metafile.inputs)
  .map((p) => p.match(/node_modules\/((?:@[^/]+\/)?[^/]+)\//)?.[1]).filter(Boolean));
const notices = [];
for (const name of [...packages].sort()) {
  const dir = join(here, "node_modules", name);
  const { version, license } = JSON.parse(await readFile(join(dir, "package.json"), "utf8"));
  const file = (await readdir(dir)).find((f) => /^licen[cs]e/i.test(f));
  const text = file ? await readFile(join(dir, file), "utf8") : `${license} (no licence file)`;
  notices.push(`${name} ${version} (${license})\n\n${text.trim()}\n`);
}
await writeFile(join(out, "licenses.txt"), notices.join(`\n${"-".repeat(72)}\n\n`));
const outputs = Object.keys(result.metafile.outputs).map((p) => basename(p));
const named = (prefix, ext) => outputs.find((p) => p.startsWith(prefix) && p.endsWith(ext));
const page = (await readFile(join(here, "src", "index.html"), "utf8"))
  .replace("{{js}}", named("app-", ".js")).replace("{{css}}", named("app-", ".css"))
  .replace("{{network}}", named("network-", ".js"));
await writeFile(join(out, "index.html"), page);
console.log(`browser spectator: ${outputs.join(", ")}, index.html, licenses.txt ` +
  "in server/static");
