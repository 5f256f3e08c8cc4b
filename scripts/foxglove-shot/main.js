// Host shell, equivalent to upstream packages/studio-web (index.tsx + Root.tsx) at v1.48:
// only supplies app configuration, layout storage and data source list to studio-base's <App/>.
(async function () {
  const S = window; // UMD exports of @foxglove/studio-base land on window
  const h = React.createElement;

  class LocalStorageAppConfiguration {
    constructor() { this.listeners = new Map(); }
    get(key) { const v = localStorage.getItem("studio.app-configuration." + key); return v == null ? undefined : JSON.parse(v); }
    async set(key, value) {
      if (value === undefined) localStorage.removeItem("studio.app-configuration." + key);
      else localStorage.setItem("studio.app-configuration." + key, JSON.stringify(value));
      for (const cb of this.listeners.get(key) ?? []) cb(value);
    }
    addChangeListener(key, cb) { if (!this.listeners.has(key)) this.listeners.set(key, new Set()); this.listeners.get(key).add(cb); }
    removeChangeListener(key, cb) { this.listeners.get(key)?.delete(cb); }
  }

  // In-memory layout storage (upstream web uses an IndexedDB-backed one)
  class MemoryLayoutStorage {
    constructor() { this.ns = new Map(); }
    m(n) { if (!this.ns.has(n)) this.ns.set(n, new Map()); return this.ns.get(n); }
    async list(n) { return [...this.m(n).values()]; }
    async get(n, id) { return this.m(n).get(id); }
    async put(n, layout) { this.m(n).set(layout.id, layout); return layout; }
    async delete(n, id) { this.m(n).delete(id); }
    async importLayouts({ fromNamespace, toNamespace }) {
      for (const l of await this.list(fromNamespace)) { await this.put(toNamespace, l); await this.delete(fromNamespace, l.id); }
    }
  }

  S.installDevtoolsFormatters();
  S.overwriteFetch();
  await S.waitForFonts();
  await S.initI18n();

  const dataSources = [
    new S.Ros1LocalBagDataSourceFactory(),
    new S.Ros2LocalBagDataSourceFactory(),
    new S.FoxgloveWebSocketDataSourceFactory(),
    new S.RosbridgeDataSourceFactory(),
    new S.UlogLocalDataSourceFactory(),
    new S.VelodyneDataSourceFactory(),
    new S.SampleNuscenesDataSourceFactory(),
    new S.McapLocalDataSourceFactory(),
    new S.RemoteDataSourceFactory(),
  ];
  const props = {
    enableLaunchPreferenceScreen: true,
    deepLinks: [window.location.href],
    dataSources,
    appConfiguration: new LocalStorageAppConfiguration(),
    layoutStorage: new MemoryLayoutStorage(),
    extensionLoaders: [new S.IdbExtensionLoader("org"), new S.IdbExtensionLoader("local")],
    enableGlobalCss: true,
  };
  ReactDOM.render(h(S.App, props), document.getElementById("root"));
})().catch((e) => { console.error("host shell failed", e); document.body.append(String(e)); });
