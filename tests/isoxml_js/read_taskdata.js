// Reads an ISO-XML TaskData zip with isoxml-js (dev4Agriculture's independent reader) and
// prints what it understood as JSON, for tests/gateway/app/test_isoxml_export.py to compare
// with sowgate's own records: the warnings, the task, the device and every time log record.
// Usage: node read_taskdata.js TASKDATA.zip
'use strict'
const { readFileSync } = require('fs')
const { ISOXMLManager } = require('isoxml')

async function main () {
  const data = readFileSync(process.argv[2])
  const manager = new ISOXMLManager()
  await manager.parseISOXMLFile(new Uint8Array(data.buffer, data.byteOffset, data.length),
    'application/zip')
  const root = manager.rootElement.attributes
  const tasks = (root.Task || []).map(task => {
    const a = task.attributes
    return {
      id: task.xmlId ?? null,
      designator: a.TaskDesignator ?? null,
      status: a.TaskStatus,
      customer: a.CustomerIdRef?.xmlId ?? null,
      farm: a.FarmIdRef?.xmlId ?? null,
      partfield: a.PartfieldIdRef?.xmlId ?? null,
      times: (a.Time || []).map(t => ({ start: t.attributes.Start, stop: t.attributes.Stop ?? null })),
      timeLogs: (a.TimeLog || []).map(tlg => {
        const info = tlg.parseBinaryFile()
        return {
          filename: tlg.attributes.Filename,
          parsingErrors: tlg.parsingErrors,
          values: info.valuesInfo.map(v => ({
            key: v.valueKey, ddi: v.DDIString ?? null, name: v.name ?? null, unit: v.unit ?? null,
            scale: v.scale ?? null, element: v.deviceElementDesignator
          })),
          records: info.timeLogs.map(r => ({
            time: r.time.getTime(),
            north: r.position.PositionNorth,
            east: r.position.PositionEast,
            status: r.position.PositionStatus,
            gpsUtcTime: r.position.GpsUtcTime,
            gpsUtcDate: r.position.GpsUtcDate,
            values: r.values
          }))
        }
      })
    }
  })
  const devices = (root.Device || []).map(d => ({
    id: d.xmlId ?? null,
    designator: d.attributes.DeviceDesignator ?? null,
    elements: (d.attributes.DeviceElement || []).map(e => ({
      id: e.xmlId ?? null, type: e.attributes.DeviceElementType, designator: e.attributes.DeviceElementDesignator
    }))
  }))
  const names = tag => (root[tag] || []).map(e => Object.values(e.attributes).find(v => typeof v === 'string' && !/^(CTR|FRM|PFD)-?\d+$/.test(v)))
  process.stdout.write(JSON.stringify({
    warnings: manager.getWarnings(),
    version: manager.options.version,
    customers: (root.Customer || []).map(c => c.attributes.CustomerLastName),
    farms: (root.Farm || []).map(f => f.attributes.FarmDesignator),
    partfields: (root.Partfield || []).map(p => ({ designator: p.attributes.PartfieldDesignator, area: p.attributes.PartfieldArea })),
    products: names('Product'),
    devices,
    tasks
  }))
}

main().catch(err => { console.error(err && err.stack ? err.stack : String(err)); process.exit(1) })
