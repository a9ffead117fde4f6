import { copyFile, mkdir, rm } from "node:fs/promises";
import { createRequire } from "node:module";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

import * as esbuild from "esbuild";

const here = dirname(fileURLToPath(import.meta.url));
const out = join(here, "..", "dist");
const require = createRequire(import.meta.url);

await rm(out, { recursive: true, force: true });
await mkdir(out, { recursive: true });

const common = { bundle: true, minify: true, sourcemap: true, logLevel: "info" };
await esbuild.build({
  ...common,
  entryPoints: [join(here, "src", "main.js")],
  outfile: join(out, "experiment.js"),
  format: "esm",
  target: ["es2022"],
});
await esbuild.build({
  ...common,
  entryPoints: [join(here, "src", "experiment.css")],
  outfile: join(out, "experiment.css"),
});

await copyFile(require.resolve("jspsych/css/jspsych.css"), join(out, "jspsych.css"));
await copyFile(join(here, "index.html"), join(out, "index.html"));
