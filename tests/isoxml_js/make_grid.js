// Writes a TaskData zip with a type 2 grid made by isoxml-js from a GeoJSON (two zones: a
// southern and a northern half at different seed rates), for the grid codec's test to read
// back: an independent writer's idea of row order and cell values.
// Usage: node make_grid.js OUT.zip [DDI]   (default 000B, count per area; 0006: mass per area)
'use strict'
const { writeFileSync } = require('fs')
const { ISOXMLManager, TAGS } = require('isoxml')

function square (w, s, e, n, rate) {
  return {
    type: 'Feature',
    properties: { RATE: rate },
    geometry: { type: 'Polygon', coordinates: [[[w, s], [e, s], [e, n], [w, n], [w, s]]] }
  }
}

async function main () {
  const manager = new ISOXMLManager()
  const task = manager.createEntityFromAttributes(TAGS.Task, { TaskStatus: '1' })
  const geoJSON = {
    type: 'FeatureCollection',
    features: [
      square(15.1000, 48.1000, 15.1040, 48.1010, 7000), // the southern half: 70 000 seeds/ha
      square(15.1000, 48.1010, 15.1040, 48.1020, 9000) // the northern half: 90 000 seeds/ha
    ]
  }
  const pdv = manager.createEntityFromAttributes(TAGS.ProcessDataVariable, {
    ProcessDataDDI: process.argv[3] || '000B', ProcessDataValue: 0
  })
  task.addGridFromGeoJSON(geoJSON, [pdv], ['RATE'])
  manager.registerEntity(task)
  manager.rootElement.attributes.Task = [task]
  writeFileSync(process.argv[2], await manager.saveISOXML())
}

main().catch(err => { console.error(err && err.stack ? err.stack : String(err)); process.exit(1) })
