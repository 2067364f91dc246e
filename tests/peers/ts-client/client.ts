// A web frontend's first hour, as a TypeScript developer writes it: types generated from ctrecon's
// openapi.yaml by openapi-typescript (into gen/api.d.ts), requests through openapi-fetch, everything
// type-checked by tsc before it runs. Simulates a fan-beam scan, submits an FBP job, follows it until it
// has finished and reads a slice of the result as PNG and as .npy. Prints one JSON line of what it saw;
// tests/generated_client.rs checks the numbers.
//
// Usage: node build/client.js http://127.0.0.1:PORT TOKEN
import createClient from "openapi-fetch";
import type { components, operations, paths } from "./gen/api.js";

type JobSummary = components["schemas"]["Job"];
type SubmitBody = operations["submitJob"]["requestBody"]["content"]["application/json"];

const [base, token] = process.argv.slice(2);
const client = createClient<paths>({
  baseUrl: base,
  headers: { Authorization: `Bearer ${token}` },
});

function fail(what: string, detail: unknown): never {
  console.error(what, JSON.stringify(detail));
  process.exit(1);
}

async function main(): Promise<void> {
  const sim = await client.POST("/v1/simulations", {
    body: {
      phantom: { table: "shepp_logan", scale_mm: 100 },
      geometry: {
        type: "parallel",
        angles: { count: 180 },
        det_count: 256,
        det_spacing_mm: 1,
      },
    },
  });
  if (!sim.data) fail("simulation refused", sim.error);
  const dataset = sim.data.id;

  const body: SubmitBody = {
    input: dataset,
    algorithm: { name: "fbp", filter: "hann" },
    grid: { nx: 128, ny: 128, dx_mm: 1.6, dy_mm: 1.6 },
    outputs: ["volume", "metrics"],
  };
  const submitted = await client.POST("/v1/jobs", { body });
  if (!submitted.data) fail("job refused", submitted.error);
  const id = submitted.data.id;

  let job: JobSummary | undefined;
  for (let i = 0; i < 600; i++) {
    const r = await client.GET("/v1/jobs/{id}", { params: { path: { id } } });
    if (!r.data) fail("job lookup failed", r.error);
    job = r.data;
    if (["succeeded", "failed", "canceled"].includes(job.status)) break;
    await new Promise((res) => setTimeout(res, 100));
  }
  if (!job || job.status !== "succeeded") fail("job did not succeed", job);

  const png = await client.GET("/v1/jobs/{id}/result/slice", {
    params: { path: { id }, query: { format: "png", ww: 0.05, wl: 0.02 } },
    parseAs: "arrayBuffer" as const,
  });
  if (!png.data) fail("slice refused", png.error);
  const bytes = new Uint8Array(png.data);
  const view = new DataView(png.data);
  const pngSignature = Array.from(bytes.slice(1, 4), (c) => String.fromCharCode(c)).join("");

  const metrics = await client.GET("/v1/jobs/{id}/result/metrics", {
    params: { path: { id } },
  });
  if (!metrics.data) fail("metrics refused", metrics.error);

  const missing = await client.GET("/v1/jobs/{id}", {
    params: { path: { id: "00000000-0000-0000-0000-000000000000" } },
  });

  console.log(
    JSON.stringify({
      dataset,
      job: id,
      status: job.status,
      png_signature: pngSignature,
      png_width: view.getUint32(16),
      png_height: view.getUint32(20),
      content_type: png.response.headers.get("content-type"),
      metrics: metrics.data,
      missing_status: missing.response.status,
      missing_code: missing.error?.code ?? null,
    }),
  );
}

main().catch((e) => fail("client error", String(e)));
