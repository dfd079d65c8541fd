// Starts the prebuilt Foxglove Studio app (its UMD bundle puts App and the data sources on `window`)
// with the project's layout (rmmdet-layout.json, copied next to this file) as the only stored layout.
// Open ?ds=foxglove-websocket&ds.url=ws://127.0.0.1:8765 to connect to the viewer at once.
// The layout is written for current Foxglove / Lichtblick, whose image panel ("Image", config under
// `imageMode`) Studio 1.48 does not have: there the same view is its "ImageViewPanel".
function studio148(layout) {
  const rename = {};
  for (const [id, config] of Object.entries(layout.configById)) {
    if (!id.startsWith("Image!")) continue;
    const mode = config.imageMode ?? {};
    const annotations = Object.entries(mode.annotations ?? {}).filter(([, a]) => a.visible).map(([t]) => t);
    const newId = "ImageViewPanel!" + id.slice("Image!".length);
    layout.configById[newId] = { cameraTopic: mode.imageTopic, enabledMarkerTopics: annotations, mode: "fit" };
    delete layout.configById[id];
    rename[id] = newId;
  }
  const walk = (node) =>
    typeof node === "string" ? rename[node] ?? node : { ...node, first: walk(node.first), second: walk(node.second) };
  layout.layout = walk(layout.layout);
  return layout;
}

(async function () {
  const S = window;
  const h = React.createElement;

  // Settings persist in the browser's localStorage.
  const listeners = new Map();
  const key = (k) => "studio.app-configuration." + k;
  const appConfiguration = {
    get: (k) => {
      const v = localStorage.getItem(key(k));
      return v == null ? undefined : JSON.parse(v);
    },
    set: async (k, v) => {
      if (v === undefined) localStorage.removeItem(key(k));
      else localStorage.setItem(key(k), JSON.stringify(v));
      for (const cb of listeners.get(k) ?? []) cb(v);
    },
    addChangeListener: (k, cb) => {
      if (!listeners.has(k)) listeners.set(k, new Set());
      listeners.get(k).add(cb);
    },
    removeChangeListener: (k, cb) => listeners.get(k)?.delete(cb),
  };

  // Layouts live in memory, seeded with the project's layout: every page load starts from it.
  const LAYOUT_ID = "rmmdet";
  const data = studio148(await (await fetch("rmmdet-layout.json", { cache: "no-store" })).json());
  const stores = new Map(); // namespace -> Map(id -> layout)
  const store = (namespace) => {
    if (!stores.has(namespace)) {
      const seeded = { id: LAYOUT_ID, name: "RMMDet", permission: "CREATOR_WRITE",
        baseline: { data, savedAt: new Date().toISOString() }, working: undefined, syncInfo: undefined };
      stores.set(namespace, new Map([[LAYOUT_ID, seeded]]));
    }
    return stores.get(namespace);
  };
  const layoutStorage = {
    list: async (n) => [...store(n).values()],
    get: async (n, id) => store(n).get(id),
    put: async (n, layout) => { store(n).set(layout.id, layout); return layout; },
    delete: async (n, id) => { store(n).delete(id); },
    importLayouts: async () => {},
    migrateUnnamespacedLayouts: async () => {},
  };

  await S.initI18n();
  const link = new URL(window.location.href);
  if (!link.searchParams.get("layoutId")) {
    link.searchParams.set("layoutId", LAYOUT_ID);
    window.history.replaceState(undefined, "", link.href);
  }
  ReactDOM.render(h(S.App, {
    deepLinks: [link.href],
    appConfiguration,
    dataSources: [new S.FoxgloveWebSocketDataSourceFactory(), new S.McapLocalDataSourceFactory()],
    layoutStorage,
    extensionLoaders: [new S.IdbExtensionLoader("local")],
    enableLaunchPreferenceScreen: false,
    enableGlobalCss: true,
  }), document.getElementById("root"));
})().catch((err) => {
  console.error("boot failed", err);
  document.body.insertAdjacentText("afterbegin", "boot failed: " + err);
});
